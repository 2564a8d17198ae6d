#include "protocol/sparkplug/sparkplug.h"

#include <array>
#include <cmath>
#include <limits>

#include "sparkplug_b.pb.h"

namespace sms::sparkplug {
namespace {

namespace wire = sms::sparkplug::wire;

constexpr std::array<std::string_view, 9> kTypeNames{"NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA",
                                                     "DDATA",  "NCMD",   "DCMD",   "STATE"};
constexpr std::array<std::string_view, 15> kDataTypeNames{"Unknown", "Int8",    "Int16",  "Int32",   "Int64",
                                                          "UInt8",   "UInt16",  "UInt32", "UInt64",  "Float",
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
// range-checked for narrow ones.
Expected<MetricValue> integer_from_wire(DataType type, std::uint64_t raw, bool narrow, const std::string& name) {
  if (is_signed(type)) {
    std::int64_t value = narrow ? std::int64_t{static_cast<std::int32_t>(static_cast<std::uint32_t>(raw))}
                                : static_cast<std::int64_t>(raw);
    const int bits = type == DataType::Int8 ? 8 : type == DataType::Int16 ? 16 : type == DataType::Int32 ? 32 : 64;
    if (bits < 64) {
      const std::int64_t low = -(std::int64_t{1} << (bits - 1));
      const std::int64_t high = (std::int64_t{1} << (bits - 1)) - 1;
      // Hosts differ in sign-extending 8/16-bit values to 32 bits; accept both spellings.
      if (value > high && value <= high * 2 + 1) value -= (high + 1) * 2;
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
  if (in.has_is_null() && in.is_null()) return MetricValue{};
  using Case = wire::Payload::Metric::ValueCase;
  switch (in.value_case()) {
    case Case::kIntValue:
      return integer_from_wire(type == DataType::Unknown ? DataType::UInt32 : type, in.int_value(), true, name);
    case Case::kLongValue:
      return integer_from_wire(type == DataType::Unknown ? DataType::UInt64 : type, in.long_value(), false, name);
    case Case::kFloatValue:
      return MetricValue{in.float_value()};
    case Case::kDoubleValue:
      return MetricValue{in.double_value()};
    case Case::kBooleanValue:
      return MetricValue{in.boolean_value()};
    case Case::kStringValue:
      return MetricValue{in.string_value()};
    case Case::kBytesValue:
    case Case::VALUE_NOT_SET:
      break;
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
  std::string text = std::string(kNamespace) + "/" + topic.group + "/" + std::string(to_string(topic.type)) + "/" +
                     topic.edge_node;
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

Expected<Payload> decode(std::span<const std::uint8_t> bytes) {
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
      return unexpected(std::string("a metric without a name (this gateway does not assign aliases, so every "
                                    "command metric must carry its name)"));
    }
    Metric metric;
    metric.name = m.name();
    metric.type = m.has_datatype() ? static_cast<DataType>(m.datatype()) : DataType::Unknown;
    if (m.has_timestamp()) metric.timestamp = m.timestamp();
    auto value = value_from_wire(m, metric.type, metric.name);
    if (!value) return unexpected(value.error());
    metric.value = std::move(*value);
    if (m.has_properties()) {
      const auto& set = m.properties();
      for (int i = 0; i < set.keys_size() && i < set.values_size(); ++i) {
        if (set.keys(i) == kEngUnitProperty && set.values(i).has_string_value()) metric.eng_unit = set.values(i).string_value();
        if (set.keys(i) == kReadOnlyProperty && set.values(i).has_boolean_value()) metric.read_only = set.values(i).boolean_value();
      }
    }
    payload.metrics.push_back(std::move(metric));
  }
  return payload;
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

}  // namespace sms::sparkplug
