#include "protocol/sparkplug/sparkplug.h"

#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <limits>

#include "sparkplug_b.pb.h"

namespace sms::sparkplug {
namespace {

namespace wire = sms::sparkplug::wire;

constexpr std::array<std::string_view, 9> kTypeNames{"NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA",
                                                     "DDATA",  "NCMD",   "DCMD",   "STATE"};
constexpr std::array<std::string_view, 15> kDataTypeNames{"Unknown", "Int8",    "Int16",  "Int32",    "Int64",
                                                          "UInt8",   "UInt16",  "UInt32", "UInt64",   "Float",
                                                          "Double",  "Boolean", "String", "DateTime", "Text"};
constexpr std::string_view kEngUnitProperty = "engUnit";
constexpr std::string_view kReadOnlyProperty = "readOnly";

std::optional<MessageType> message_type(std::string_view name) {
  for (std::size_t i = 0; i < kTypeNames.size(); ++i) {
    if (kTypeNames[i] == name) return static_cast<MessageType>(i);
  }
  return std::nullopt;
}

bool is_signed(DataType type) {
  return type == DataType::Int8 || type == DataType::Int16 || type == DataType::Int32 || type == DataType::Int64;
}
// The types carried in int_value (32 bits); the 64-bit ones use long_value (spec §6.4.16).
bool is_narrow(DataType type) {
  return type == DataType::Int8 || type == DataType::Int16 || type == DataType::Int32 || type == DataType::UInt8 ||
         type == DataType::UInt16 || type == DataType::UInt32;
}

void add_property(wire::Payload::PropertySet& set, std::string_view key, DataType type) {
  set.add_keys(std::string(key));
  set.add_values()->set_type(static_cast<std::uint32_t>(type));
}

void set_value(wire::Payload::Metric& out, const Metric& metric) {
  std::visit(
      [&](const auto& value) {
        using T = std::decay_t<decltype(value)>;
        if constexpr (std::is_same_v<T, std::monostate>) {
          out.set_is_null(true);
        } else if constexpr (std::is_same_v<T, std::int64_t> || std::is_same_v<T, std::uint64_t>) {
          // Signed narrow types ride as their two's complement in 32 bits (spec §6.4.16).
          if (is_narrow(metric.type)) {
            out.set_int_value(static_cast<std::uint32_t>(value));
          } else {
            out.set_long_value(static_cast<std::uint64_t>(value));
          }
        } else if constexpr (std::is_same_v<T, float>) {
          out.set_float_value(value);
        } else if constexpr (std::is_same_v<T, double>) {
          out.set_double_value(value);
        } else if constexpr (std::is_same_v<T, bool>) {
          out.set_boolean_value(value);
        } else {
          out.set_string_value(value);
        }
      },
      metric.value);
}

// An int_value or long_value read back as the declared type: sign-extended for signed types,
// range-checked for narrow ones. `low_bits_too`: an Int8/Int16 may also come as its 8/16 low bits
// only (hosts differ); not for a type taken from the birth, where nothing says how the sender
// meant it.
Expected<MetricValue> integer_from_wire(DataType type, std::uint64_t raw, bool narrow, bool low_bits_too,
                                        const std::string& name) {
  if (is_signed(type)) {
    std::int64_t value = narrow ? std::int64_t{static_cast<std::int32_t>(static_cast<std::uint32_t>(raw))}
                                : static_cast<std::int64_t>(raw);
    const int bits = type == DataType::Int8 ? 8 : type == DataType::Int16 ? 16 : type == DataType::Int32 ? 32 : 64;
    if (bits < 64) {
      const std::int64_t low = -(std::int64_t{1} << (bits - 1));
      const std::int64_t high = (std::int64_t{1} << (bits - 1)) - 1;
      // Hosts differ in sign-extending 8/16-bit values to 32 bits; accept both spellings.
      if (low_bits_too && value > high && value <= high * 2 + 1) value -= (high + 1) * 2;
      if (value < low || value > high) {
        return unexpected("metric '" + name + "': " + std::to_string(value) + " does not fit " +
                          std::string(to_string(type)));
      }
    }
    return MetricValue{value};
  }
  const int bits = type == DataType::UInt8 ? 8 : type == DataType::UInt16 ? 16 : type == DataType::UInt32 ? 32 : 64;
  if (bits < 64 && raw >> bits != 0) {
    return unexpected("metric '" + name + "': " + std::to_string(raw) + " does not fit " +
                      std::string(to_string(type)));
  }
  return MetricValue{raw};
}

Expected<MetricValue> value_from_wire(const wire::Payload::Metric& in, DataType type, const std::string& name) {
  const bool declared = in.has_datatype() && in.datatype() != 0;
  if (in.has_is_null() && in.is_null()) return MetricValue{};
  using Case = wire::Payload::Metric::ValueCase;
  switch (in.value_case()) {
    case Case::kIntValue:
      return integer_from_wire(type == DataType::Unknown ? DataType::UInt32 : type, in.int_value(), true, declared,
                               name);
    case Case::kLongValue:
      return integer_from_wire(type == DataType::Unknown ? DataType::UInt64 : type, in.long_value(), false, declared,
                               name);
    case Case::kFloatValue: return MetricValue{in.float_value()};
    case Case::kDoubleValue: return MetricValue{in.double_value()};
    case Case::kBooleanValue: return MetricValue{in.boolean_value()};
    case Case::kStringValue: return MetricValue{in.string_value()};
    case Case::kBytesValue:
    case Case::VALUE_NOT_SET: break;
  }
  return MetricValue{};
}

}  // namespace

std::string_view to_string(MessageType type) { return kTypeNames.at(static_cast<std::size_t>(type)); }

std::string_view to_string(DataType type) {
  const auto index = static_cast<std::size_t>(type);
  return index < kDataTypeNames.size() ? kDataTypeNames[index] : "Unknown";
}

bool valid_id(std::string_view id) { return !id.empty() && id.find_first_of("/+#") == std::string_view::npos; }

std::string topic_text(const Topic& topic) {
  std::string text =
      std::string(kNamespace) + "/" + topic.group + "/" + std::string(to_string(topic.type)) + "/" + topic.edge_node;
  if (!topic.device.empty()) text += "/" + topic.device;
  return text;
}

std::optional<Topic> parse_topic(std::string_view text) {
  std::vector<std::string_view> parts;
  while (true) {
    const auto slash = text.find('/');
    parts.push_back(text.substr(0, slash));
    if (slash == std::string_view::npos) break;
    text.remove_prefix(slash + 1);
  }
  if (parts.size() < 4 || parts.size() > 5 || parts[0] != kNamespace) return std::nullopt;
  const auto type = message_type(parts[2]);
  if (!type || *type == MessageType::State) return std::nullopt;
  for (const auto part : parts) {
    if (!valid_id(part)) return std::nullopt;
  }
  const bool device_type = *type == MessageType::DBirth || *type == MessageType::DDeath ||
                           *type == MessageType::DData || *type == MessageType::DCmd;
  if (device_type != (parts.size() == 5)) return std::nullopt;
  Topic topic{std::string(parts[1]), *type, std::string(parts[3]), ""};
  if (device_type) topic.device = std::string(parts[4]);
  return topic;
}

Bytes encode(const Payload& payload) {
  wire::Payload out;
  if (payload.timestamp) out.set_timestamp(*payload.timestamp);
  if (payload.seq) out.set_seq(*payload.seq);
  for (const auto& metric : payload.metrics) {
    auto& m = *out.add_metrics();
    m.set_name(metric.name);
    m.set_datatype(static_cast<std::uint32_t>(metric.type));
    if (metric.timestamp) m.set_timestamp(*metric.timestamp);
    set_value(m, metric);
    if (!metric.eng_unit.empty() || metric.read_only) {
      auto& properties = *m.mutable_properties();
      if (!metric.eng_unit.empty()) {
        add_property(properties, kEngUnitProperty, DataType::String);
        properties.mutable_values(properties.values_size() - 1)->set_string_value(metric.eng_unit);
      }
      if (metric.read_only) {
        add_property(properties, kReadOnlyProperty, DataType::Boolean);
        properties.mutable_values(properties.values_size() - 1)->set_boolean_value(true);
      }
    }
  }
  Bytes bytes(out.ByteSizeLong());
  out.SerializeToArray(bytes.data(), static_cast<int>(bytes.size()));
  return bytes;
}

Expected<Payload> decode(std::span<const std::uint8_t> bytes, const BirthTypes& birth_types) {
  if (bytes.size() > static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    return unexpected(std::string("payload too large"));
  }
  wire::Payload in;
  if (!in.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
    return unexpected("not a Sparkplug B payload (protobuf decoding failed on " + std::to_string(bytes.size()) +
                      " bytes)");
  }
  Payload payload;
  if (in.has_timestamp()) payload.timestamp = in.timestamp();
  if (in.has_seq()) payload.seq = in.seq();
  for (const auto& m : in.metrics()) {
    if (!m.has_name() || m.name().empty()) {
      return unexpected(
          std::string("a metric without a name (this gateway does not assign aliases, so every "
                      "command metric must carry its name)"));
    }
    Metric metric;
    metric.name = m.name();
    metric.type = m.has_datatype() ? static_cast<DataType>(m.datatype()) : DataType::Unknown;
    if (metric.type == DataType::Unknown && birth_types) metric.type = birth_types(metric.name);
    if (m.has_timestamp()) metric.timestamp = m.timestamp();
    auto value = value_from_wire(m, metric.type, metric.name);
    if (!value) return unexpected(value.error());
    metric.value = std::move(*value);
    if (m.has_properties()) {
      const auto& set = m.properties();
      for (int i = 0; i < set.keys_size() && i < set.values_size(); ++i) {
        if (set.keys(i) == kEngUnitProperty && set.values(i).has_string_value())
          metric.eng_unit = set.values(i).string_value();
        if (set.keys(i) == kReadOnlyProperty && set.values(i).has_boolean_value())
          metric.read_only = set.values(i).boolean_value();
      }
    }
    payload.metrics.push_back(std::move(metric));
  }
  return payload;
}

std::optional<IntegerRange> integer_range(DataType type) {
  constexpr auto kMax64 = std::numeric_limits<std::int64_t>::max();
  switch (type) {
    case DataType::Int8: return IntegerRange{-128, 127};
    case DataType::Int16: return IntegerRange{-32768, 32767};
    case DataType::Int32:
      return IntegerRange{std::numeric_limits<std::int32_t>::min(), std::numeric_limits<std::int32_t>::max()};
    case DataType::Int64: return IntegerRange{std::numeric_limits<std::int64_t>::min(), kMax64};
    case DataType::UInt8: return IntegerRange{0, 255};
    case DataType::UInt16: return IntegerRange{0, 65535};
    case DataType::UInt32: return IntegerRange{0, std::numeric_limits<std::uint32_t>::max()};
    case DataType::UInt64: return IntegerRange{0, kMax64};
    default: return std::nullopt;
  }
}

std::optional<std::int64_t> integer_value(const MetricValue& value) {
  if (const auto* v = std::get_if<std::int64_t>(&value)) return *v;
  if (const auto* v = std::get_if<std::uint64_t>(&value)) {
    if (*v > static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max())) return std::nullopt;
    return static_cast<std::int64_t>(*v);
  }
  if (const auto* v = std::get_if<bool>(&value)) return *v ? 1 : 0;
  const auto whole = [](double d) -> std::optional<std::int64_t> {
    if (!std::isfinite(d) || d != std::trunc(d) || std::fabs(d) > 9.0e15) return std::nullopt;
    return static_cast<std::int64_t>(d);
  };
  if (const auto* v = std::get_if<float>(&value)) return whole(*v);
  if (const auto* v = std::get_if<double>(&value)) return whole(*v);
  return std::nullopt;
}

std::string state_topic(std::string_view host_id) { return std::string(kNamespace) + "/STATE/" + std::string(host_id); }

namespace {

// Just enough JSON for a STATE payload: one object whose values are read (booleans, numbers) or
// skipped (strings, nested objects and arrays, null).
class JsonReader {
 public:
  explicit JsonReader(std::string_view text) : text_(text) {}

  bool eat(char c) {
    skip_space();
    if (at_ < text_.size() && text_[at_] == c) {
      ++at_;
      return true;
    }
    return false;
  }
  bool done() {
    skip_space();
    return at_ == text_.size();
  }
  std::optional<std::string> string() {
    if (!eat('"')) return std::nullopt;
    std::string out;
    while (at_ < text_.size() && text_[at_] != '"') {
      if (text_[at_] == '\\') {
        if (++at_ >= text_.size()) return std::nullopt;
        if (text_[at_] == 'u') {  // a key with \u escapes matches none of ours: keep it unequal
          if (at_ + 4 >= text_.size()) return std::nullopt;
          out += '?';
          at_ += 4;
        } else {
          out += text_[at_];
        }
      } else {
        out += text_[at_];
      }
      ++at_;
    }
    if (at_ >= text_.size()) return std::nullopt;
    ++at_;
    return out;
  }
  std::optional<bool> boolean() {
    skip_space();
    for (const bool value : {true, false}) {
      const std::string_view word = value ? "true" : "false";
      if (text_.substr(at_, word.size()) == word) {
        at_ += word.size();
        return value;
      }
    }
    return std::nullopt;
  }
  // A JSON number; `whole` is set when it is a whole number that fits 64 bits unsigned.
  bool number(std::optional<std::uint64_t>& whole) {
    skip_space();
    const std::size_t start = at_;
    while (at_ < text_.size() && (std::isdigit(static_cast<unsigned char>(text_[at_])) || text_[at_] == '-' ||
                                  text_[at_] == '+' || text_[at_] == '.' || text_[at_] == 'e' || text_[at_] == 'E')) {
      ++at_;
    }
    if (at_ == start) return false;
    std::uint64_t value = 0;
    const auto* first = text_.data() + start;
    const auto* last = text_.data() + at_;
    const auto [end, error] = std::from_chars(first, last, value);
    if (error == std::errc() && end == last) whole = value;
    return true;
  }
  bool skip_value(int depth = 0) {
    if (depth > 16) return false;
    skip_space();
    if (at_ >= text_.size()) return false;
    const char c = text_[at_];
    if (c == '"') return string().has_value();
    if (c == '{' || c == '[') {
      const char close = c == '{' ? '}' : ']';
      ++at_;
      if (eat(close)) return true;
      do {
        if (c == '{' && (!string() || !eat(':'))) return false;
        if (!skip_value(depth + 1)) return false;
      } while (eat(','));
      return eat(close);
    }
    if (boolean()) return true;
    if (text_.substr(at_, 4) == "null") {
      at_ += 4;
      return true;
    }
    std::optional<std::uint64_t> ignored;
    return number(ignored);
  }

 private:
  void skip_space() {
    while (at_ < text_.size() && std::isspace(static_cast<unsigned char>(text_[at_]))) ++at_;
  }
  std::string_view text_;
  std::size_t at_ = 0;
};

}  // namespace

Expected<HostState> parse_host_state(std::string_view json) {
  JsonReader reader(json);
  const auto not_json = [] {
    return unexpected(
        std::string(R"(not a Sparkplug 3.0 STATE payload (expected JSON {"online": true|false, "timestamp": <ms>}))"));
  };
  if (!reader.eat('{')) return not_json();
  std::optional<bool> online;
  std::optional<std::uint64_t> timestamp;
  bool timestamp_seen = false;
  if (!reader.eat('}')) {
    do {
      const auto key = reader.string();
      if (!key || !reader.eat(':')) return not_json();
      if (*key == "online") {
        online = reader.boolean();
        if (!online) return unexpected(std::string("STATE: `online` is not true or false"));
      } else if (*key == "timestamp") {
        timestamp_seen = true;
        if (!reader.number(timestamp)) return not_json();
      } else if (!reader.skip_value()) {
        return not_json();
      }
    } while (reader.eat(','));
    if (!reader.eat('}')) return not_json();
  }
  if (!reader.done()) return not_json();
  if (!online) return unexpected(std::string("STATE: no `online` key"));
  if (!timestamp) {
    return unexpected(std::string(timestamp_seen ? "STATE: `timestamp` is not a whole number of ms since the epoch"
                                                 : "STATE: no `timestamp` key"));
  }
  return HostState{*online, *timestamp};
}

std::string host_state_json(const HostState& state) {
  return std::string(R"({"online":)") + (state.online ? "true" : "false") + R"(,"timestamp":)" +
         std::to_string(state.timestamp) + "}";
}

}  // namespace sms::sparkplug
