#include "config/load.h"

#include <yaml-cpp/eventhandler.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <span>
#include <sstream>
#include <utility>

#include "config/names.h"
#include "modbus_map/baud_tables.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"
#include "modbus_map/timed_move.h"
#include "protocol/modbus_pdu.h"

namespace sms::config {
namespace {

using modbus_map::TableId;
using modbus_map::TableSpec;
using protocol::BusProtocol;

// ---- the keys allowed at each place (config/README.md) ----

constexpr std::array<std::string_view, 9> kTopKeys{
    "modbus_tcp", "buses", "servos", "sync_groups", "logging", "mqtt", "state_dir", "modbus_rtu_slave", "console"};
constexpr std::array<std::string_view, 11> kModbusTcpKeys{"listen",
                                                          "max_connections",
                                                          "max_waiting",
                                                          "max_waiting_per_address",
                                                          "first_request_timeout_ms",
                                                          "idle_timeout_s",
                                                          "gateway_unit_id",
                                                          "request_queue_depth",
                                                          "allow",
                                                          "plain",
                                                          "tls"};
constexpr std::array<std::string_view, 10> kTlsKeys{"listen",         "certificate",
                                                    "private_key",    "ca",
                                                    "roles",          "default_role",
                                                    "role_names",     "handshake_timeout_ms",
                                                    "max_handshakes", "max_handshakes_per_address"};
constexpr std::array<std::string_view, 22> kBusKeys{"name",
                                                    "device",
                                                    "protocol",
                                                    "baud",
                                                    "parity",
                                                    "stop_bits",
                                                    "response_timeout_ms",
                                                    "retries",
                                                    "poll_period_ms",
                                                    "offline_probe_period_ms",
                                                    "reopen_period_ms",
                                                    "poll_fields",
                                                    "poll_range",
                                                    "rs485",
                                                    "rts",
                                                    "rts_delay_us",
                                                    "byte_timeout_ms",
                                                    "frame_gap",
                                                    "watchdog",
                                                    "on_start",
                                                    "on_stop",
                                                    "stop_deceleration"};
constexpr std::array<std::string_view, 3> kWatchdogKeys{"timeout_ms", "feed", "action"};
// Keys of kBusKeys that only a modbus-rtu bus takes.
constexpr std::array<std::string_view, 5> kModbusRtuOnlyKeys{"rs485", "rts", "rts_delay_us", "byte_timeout_ms",
                                                             "frame_gap"};
constexpr std::array<std::string_view, 2> kPollRangeKeys{"start", "count"};
constexpr std::array<std::string_view, 11> kServoKeys{
    "unit",           "bus",       "id",   "table",     "profile",          "byte_order",
    "response_level", "read_only", "name", "safe_stop", "stop_deceleration"};
constexpr std::array<std::string_view, 6> kSyncGroupKeys{"name",      "field",  "members", "holding_register_start",
                                                         "move_time", "stretch"};
constexpr std::array<std::string_view, 3> kLoggingKeys{"level", "format", "metrics_listen"};
constexpr std::array<std::string_view, 16> kMqttKeys{"broker",
                                                     "group_id",
                                                     "edge_node_id",
                                                     "client_id",
                                                     "username",
                                                     "password_file",
                                                     "tls",
                                                     "keepalive_s",
                                                     "role",
                                                     "data_period_ms",
                                                     "report_period_s",
                                                     "deadband",
                                                     "reconnect_min_ms",
                                                     "reconnect_max_ms",
                                                     "enabled",
                                                     "primary_host_id"};
constexpr std::array<std::string_view, 3> kMqttTlsKeys{"ca", "certificate", "private_key"};
constexpr std::array<std::string_view, 12> kRtuSlaveKeys{
    "device", "baud",         "parity", "stop_bits", "frame_gap",        "rs485",
    "rts",    "rts_delay_us", "units",  "role",      "reopen_period_ms", "echo"};

constexpr std::array<std::string_view, 7> kConsoleKeys{"listen",        "tls",   "certificate",      "key",
                                                       "insecure_http", "users", "session_timeout_s"};
constexpr std::array<std::string_view, 3> kConsoleUserKeys{"name", "role", "password_hash"};

constexpr std::string_view kPassthroughTable = "passthrough";
constexpr std::uint8_t kMaxUnitId = 247;         // Modbus slave addresses
constexpr std::uint8_t kMaxPacketServoId = 253;  // 254 is the broadcast ID (docs/PROTOCOL.md §1)
// A sync group is one FC16 write; a modbus-rtu poll block one FC03.
constexpr std::size_t kMaxWriteRegisters = protocol::modbus_limits::kWriteRegisters;
constexpr std::uint16_t kMaxRtuReadRegisters = protocol::modbus_limits::kReadRegisters;
constexpr std::uint16_t kMaxPacketReadBytes = 253;  // READ reply LEN = count + 2 fits one byte

// Where the loader is: a node, the place to blame for it, and its path in the document.
struct Value {
  YAML::Node node;
  YAML::Mark mark;
  std::string path;
};

// yaml-cpp marks an empty value (`key:` followed by nothing) at the next token, which may be
// lines away; blame the key instead.
Value entry_value(const YAML::Node& key, const YAML::Node& value, std::string path) {
  return Value{value, value.IsNull() ? key.Mark() : value.Mark(), std::move(path)};
}

struct Failure {
  ConfigError error;
};

// Well-formed UTF-8 without control characters: such strings would not survive a dump (the YAML
// writer replaces them) and would garble logs and metrics labels.
bool is_printable_utf8(std::string_view text) {
  for (std::size_t i = 0; i < text.size();) {
    const auto lead = static_cast<unsigned char>(text[i]);
    if (lead < 0x80) {
      if (lead < 0x20 || lead == 0x7F) return false;
      ++i;
      continue;
    }
    std::size_t length = 0;
    std::uint32_t code = 0;
    if ((lead & 0xE0) == 0xC0) {
      length = 2, code = lead & 0x1F;
    } else if ((lead & 0xF0) == 0xE0) {
      length = 3, code = lead & 0x0F;
    } else if ((lead & 0xF8) == 0xF0) {
      length = 4, code = lead & 0x07;
    } else {
      return false;
    }
    if (i + length > text.size()) return false;
    for (std::size_t k = 1; k < length; ++k) {
      const auto next = static_cast<unsigned char>(text[i + k]);
      if ((next & 0xC0) != 0x80) return false;
      code = (code << 6) | (next & 0x3F);
    }
    static constexpr std::uint32_t kSmallest[] = {0, 0, 0x80, 0x800, 0x10000};
    if (code < kSmallest[length] || code > 0x10FFFF || (code >= 0xD800 && code <= 0xDFFF)) return false;
    if (code >= 0x80 && code < 0xA0) return false;  // C1 controls
    i += length;
  }
  return true;
}

std::string join(std::span<const std::string_view> names) {
  std::string text;
  for (const auto name : names) {
    if (!text.empty()) text += ", ";
    text += name;
  }
  return text;
}

template <typename Range>
std::string join_numbers(const Range& numbers) {
  std::string text;
  for (const auto number : numbers) {
    if (!text.empty()) text += ", ";
    text += std::to_string(number);
  }
  return text;
}

std::string place(const YAML::Mark& mark) {
  return "line " + std::to_string(mark.line + 1) + ", column " + std::to_string(mark.column + 1);
}

std::size_t edit_distance(std::string_view a, std::string_view b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diagonal = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t above = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = above;
    }
  }
  return row[b.size()];
}

// The allowed name closest to `name`, when it is close enough to be a typo.
std::optional<std::string_view> closest(std::string_view name, std::span<const std::string_view> allowed) {
  std::optional<std::string_view> best;
  std::size_t best_distance = std::max<std::size_t>(2, name.size() / 3) + 1;
  for (const auto candidate : allowed) {
    const auto distance = edit_distance(name, candidate);
    if (distance < best_distance) {
      best = candidate;
      best_distance = distance;
    }
  }
  if (best) return best;
  // A longer or shorter spelling of an allowed key (`baudrate` for `baud`).
  std::size_t best_prefix = 3;
  for (const auto candidate : allowed) {
    const auto limit = std::min(name.size(), candidate.size());
    std::size_t common = 0;
    while (common < limit && name[common] == candidate[common]) ++common;
    if (common > best_prefix) {
      best = candidate;
      best_prefix = common;
    }
  }
  return best;
}

std::string describe(const YAML::Node& node) {
  switch (node.Type()) {
    case YAML::NodeType::Null:
    case YAML::NodeType::Undefined: return "nothing";
    case YAML::NodeType::Sequence: return "a list";
    case YAML::NodeType::Map: return "a map";
    case YAML::NodeType::Scalar: break;
  }
  if (node.Tag() == "!") return "the quoted string \"" + node.Scalar() + "\"";
  return "`" + node.Scalar() + "`";
}

// Plain (unquoted) scalars, or ones tagged with the matching core type, are numbers and
// booleans; a quoted "5020" is a string (YAML's rule) and is refused with a hint.
bool plain_or_tagged(const YAML::Node& node, std::string_view core_tag) {
  return node.Tag() == "?" || node.Tag() == core_tag;
}

std::optional<std::int64_t> parse_integer(std::string_view text) {
  bool negative = false;
  if (!text.empty() && (text.front() == '-' || text.front() == '+')) {
    negative = text.front() == '-';
    text.remove_prefix(1);
  }
  int base = 10;
  if (text.size() > 2 && text[0] == '0' && (text[1] == 'x' || text[1] == 'X')) {
    base = 16;
    text.remove_prefix(2);
  }
  if (text.empty() || text.front() == '-' || text.front() == '+') return std::nullopt;
  std::int64_t value = 0;
  const auto* end = text.data() + text.size();
  const auto [stop, error] = std::from_chars(text.data(), end, value, base);
  if (error != std::errc{} || stop != end) return std::nullopt;
  return negative ? -value : value;
}

// YAML 1.1 and 1.2 spellings both: configs in the field are written either way.
std::optional<bool> parse_bool(std::string_view text) {
  static constexpr std::array<std::string_view, 9> kTrue{"true", "True", "TRUE", "yes", "Yes", "YES", "on", "On", "ON"};
  static constexpr std::array<std::string_view, 9> kFalse{"false", "False", "FALSE", "no", "No",
                                                          "NO",    "off",   "Off",   "OFF"};
  if (std::find(kTrue.begin(), kTrue.end(), text) != kTrue.end()) return true;
  if (std::find(kFalse.begin(), kFalse.end(), text) != kFalse.end()) return false;
  return std::nullopt;
}

bool valid_bus_name(std::string_view name) {
  return !name.empty() && std::all_of(name.begin(), name.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-' ||
           c == '.';
  });
}

std::string table_names_text() {
  std::string text;
  for (const auto* spec : modbus_map::all_tables()) {
    text += std::string(spec->name) + ", ";
  }
  return text + std::string(kPassthroughTable);
}

std::string field_names_text(const TableSpec& table) {
  std::string text;
  for (const auto& field : table.fields) {
    if (!text.empty()) text += ", ";
    text += field.name;
  }
  return text;
}

// Places of a servo's nodes, kept for messages that name two places.
struct ServoPlaces {
  YAML::Mark item;
  YAML::Mark unit;  // the `unit` value, or the `id` value when the unit defaults to it
  YAML::Mark id;
  bool unit_given = false;
  std::string path;
};

struct BusPlaces {
  YAML::Mark name;
  YAML::Mark device;
  std::vector<Value> poll_fields;
  std::optional<Value> poll_range;
  std::string path;
};

class MapReader;

// Reads the document into a Config, checking as it goes; the first problem throws Failure.
class Loader {
 public:
  explicit Loader(std::string file) : file_(std::move(file)) {}

  Config load(const YAML::Node& root);

  [[noreturn]] void fail(const YAML::Mark& mark, std::string message) const {
    ConfigError error;
    error.file = file_;
    if (!mark.is_null()) {
      error.line = static_cast<std::uint32_t>(mark.line + 1);
      error.column = static_cast<std::uint32_t>(mark.column + 1);
    }
    error.message = std::move(message);
    throw Failure{std::move(error)};
  }

  // ---- scalars ----

  std::int64_t integer(const Value& value, std::int64_t min, std::int64_t max) const {
    const auto range = std::to_string(min) + ".." + std::to_string(max);
    if (!value.node.IsScalar()) {
      fail(value.mark, value.path + ": expected an integer (" + range + "), got " + describe(value.node));
    }
    if (!plain_or_tagged(value.node, "tag:yaml.org,2002:int")) {
      fail(value.mark, value.path + ": expected an integer (" + range + "), got " + describe(value.node) +
                           "; write numbers without quotes");
    }
    const auto parsed = parse_integer(value.node.Scalar());
    if (!parsed) {
      fail(value.mark, value.path + ": expected an integer (" + range + "), got " + describe(value.node));
    }
    if (*parsed < min || *parsed > max) {
      fail(value.mark, value.path + ": " + value.node.Scalar() + " is outside " + range);
    }
    return *parsed;
  }

  template <typename Duration>
  Duration duration(const Value& value, std::int64_t min, std::int64_t max) const {
    return Duration{integer(value, min, max)};
  }

  bool boolean(const Value& value) const {
    if (value.node.IsScalar() && plain_or_tagged(value.node, "tag:yaml.org,2002:bool")) {
      if (const auto parsed = parse_bool(value.node.Scalar())) return *parsed;
    }
    fail(value.mark, value.path + ": expected true or false, got " + describe(value.node));
  }

  std::string string(const Value& value) const {
    if (!value.node.IsScalar()) {
      fail(value.mark, value.path + ": expected a string, got " + describe(value.node));
    }
    if (value.node.Scalar().empty()) fail(value.mark, value.path + ": must not be empty");
    if (!is_printable_utf8(value.node.Scalar())) {
      fail(value.mark, value.path +
                           ": must be printable UTF-8 text (it has a control character or "
                           "bytes that are not UTF-8); names end up in logs and metrics labels");
    }
    return value.node.Scalar();
  }

  template <typename E, std::size_t N>
  E choice(const Value& value, const std::array<detail::Named<E>, N>& names) const {
    if (value.node.IsScalar()) {
      if (const auto parsed = detail::value_of(names, value.node.Scalar())) return *parsed;
    }
    fail(value.mark, value.path + ": expected one of " + detail::names_text(names) + ", got " + describe(value.node));
  }

  HostPort host_port(const Value& value) const {
    const auto parsed = parse_host_port(string(value));
    if (!parsed) fail(value.mark, value.path + ": " + parsed.error());
    return *parsed;
  }

  std::vector<Value> list(const Value& value) const {
    if (!value.node.IsSequence()) {
      fail(value.mark, value.path + ": expected a list, got " + describe(value.node) +
                           (value.node.IsNull() ? " (write [] for an empty list)" : ""));
    }
    std::vector<Value> items;
    std::size_t index = 0;
    for (const auto& item : value.node) {
      items.push_back(
          Value{item, item.IsNull() ? value.mark : item.Mark(), value.path + "[" + std::to_string(index++) + "]"});
    }
    return items;
  }

  // A map of names to values ({plc-1: operate}): `expected` describes it for the error; each
  // name is a non-empty string given once; `each` gets the name, its mark and its value.
  void named_map(const Value& value, const std::string& expected,
                 const std::function<void(const std::string&, const YAML::Mark&, const Value&)>& each) const {
    if (!value.node.IsMap()) fail(value.mark, value.path + ": expected " + expected + ", got " + describe(value.node));
    std::vector<std::pair<std::string, YAML::Mark>> seen;
    for (const auto& entry : value.node) {
      const YAML::Node& name_node = entry.first;
      const std::string name = string(Value{name_node, name_node.Mark(), value.path});
      for (const auto& [other, mark] : seen) {
        if (other == name)
          fail(name_node.Mark(), value.path + ": `" + name + "` is given twice (first at " + place(mark) + ")");
      }
      seen.emplace_back(name, name_node.Mark());
      each(name, name_node.Mark(), entry_value(name_node, entry.second, value.path + "." + name));
    }
  }

 private:
  ModbusTcpConfig parse_modbus_tcp(const Value& value);
  TlsConfig parse_tls(const Value& value);
  void parse_buses(const Value& value, Config& config);
  BusConfig parse_bus(const Value& value, BusPlaces& places);
  void parse_servos(const Value& value, Config& config);
  ServoConfig parse_servo(const Value& value, const Config& config, ServoPlaces& places);
  void check_second_view(const ServoConfig& servo, const ServoPlaces& places, const ServoConfig& other,
                         const ServoPlaces& other_places) const;
  void check_poll_selections(const Config& config);
  void parse_sync_groups(const Value& value, Config& config);
  SyncGroupConfig parse_sync_group(const MapReader& keys, const Config& config);
  void check_timed_move_members(const Value& value, const SyncGroupConfig& group, const Config& config);
  LoggingConfig parse_logging(const Value& value);
  std::optional<MqttConfig> parse_mqtt(const Value& value, const Config& config);
  void parse_rtu_slaves(const Value& value, Config& config);
  ConsoleConfig parse_console(const Value& value, const Config& config);
  RtuSlaveConfig parse_rtu_slave(const Value& value, const Config& config);
  // rs485, rts, rts_delay_us and frame_gap: the same keys on a modbus-rtu bus and an upstream port.
  void parse_rtu_line(const MapReader& keys, const Value& value, ModbusRtuOptions& line) const;

  std::string file_;
  std::optional<YAML::Mark> gateway_unit_mark_;
  std::vector<BusPlaces> bus_places_;
  std::vector<ServoPlaces> servo_places_;
  std::vector<YAML::Mark> group_start_marks_;
};

// A map node checked for shape on construction: keys are plain names, none twice, none unknown.
class MapReader {
 public:
  MapReader(const Loader& loader, const Value& map, std::span<const std::string_view> allowed)
      : loader_(loader), map_(map) {
    if (!map.node.IsMap()) {
      loader.fail(map.mark, map.path + ": expected a map of keys (" + join(allowed) + "), got " + describe(map.node));
    }
    for (const auto& entry : map.node) {
      const YAML::Node& key = entry.first;
      if (!key.IsScalar()) loader.fail(key.Mark(), "keys are plain names, got " + describe(key) + " " + where());
      const std::string& name = key.Scalar();
      if (std::find(allowed.begin(), allowed.end(), name) == allowed.end()) {
        std::string message = "unknown key `" + name + "` " + where();
        if (const auto suggestion = closest(name, allowed)) {
          message += " (did you mean `" + std::string(*suggestion) + "`?)";
        }
        loader.fail(key.Mark(), message + "; allowed keys here: " + join(allowed));
      }
      for (const auto& [seen, seen_key] : keys_) {
        if (seen == name) {
          loader.fail(key.Mark(), "key `" + name + "` given twice " + where() + " (first at " + place(seen_key) + ")");
        }
      }
      keys_.emplace_back(name, key.Mark());
      entries_.push_back(entry_value(key, entry.second, child_path(name)));
    }
  }

  std::optional<Value> find(std::string_view key) const {
    for (std::size_t i = 0; i < keys_.size(); ++i) {
      if (keys_[i].first == key) return entries_[i];
    }
    return std::nullopt;
  }

  Value require(std::string_view key) const {
    if (auto value = find(key)) return *value;
    loader_.fail(map_.mark, "missing required key `" + std::string(key) + "` " + where());
  }

  YAML::Mark key_mark(std::string_view key) const {
    for (const auto& [name, mark] : keys_) {
      if (name == key) return mark;
    }
    return map_.mark;
  }

 private:
  std::string where() const { return map_.path.empty() ? "at the top level" : "in " + map_.path; }

  std::string child_path(std::string_view key) const {
    return map_.path.empty() ? std::string(key) : map_.path + "." + std::string(key);
  }

  const Loader& loader_;
  const Value& map_;
  std::vector<std::pair<std::string, YAML::Mark>> keys_;
  std::vector<Value> entries_;
};

// ---- sections ----

Config Loader::load(const YAML::Node& root) {
  const Value top{root, root.Mark(), ""};
  if (!root.IsMap()) {
    fail(root.Mark(), "expected a map of sections (" + join(kTopKeys) + "), got " + describe(root));
  }
  const MapReader sections(*this, top, kTopKeys);
  Config config;
  if (const auto value = sections.find("modbus_tcp")) config.modbus_tcp = parse_modbus_tcp(*value);
  parse_buses(sections.require("buses"), config);
  parse_servos(sections.require("servos"), config);
  check_poll_selections(config);
  if (const auto value = sections.find("sync_groups")) parse_sync_groups(*value, config);
  if (const auto value = sections.find("logging")) config.logging = parse_logging(*value);
  if (const auto value = sections.find("mqtt")) config.mqtt = parse_mqtt(*value, config);
  if (const auto value = sections.find("state_dir")) config.state_dir = string(*value);
  if (const auto value = sections.find("modbus_rtu_slave")) parse_rtu_slaves(*value, config);
  if (const auto value = sections.find("console")) config.console = parse_console(*value, config);
  return config;
}

ModbusTcpConfig Loader::parse_modbus_tcp(const Value& value) {
  const MapReader keys(*this, value, kModbusTcpKeys);
  ModbusTcpConfig tcp;
  if (const auto v = keys.find("listen")) tcp.listen = host_port(*v);
  if (const auto v = keys.find("max_connections")) {
    tcp.max_connections = static_cast<std::size_t>(integer(*v, 1, static_cast<std::int64_t>(kMaxConnectionsLimit)));
  }
  if (const auto v = keys.find("max_waiting")) {
    tcp.max_waiting = static_cast<std::size_t>(integer(*v, 1, static_cast<std::int64_t>(kMaxConnectionsLimit)));
  }
  if (const auto v = keys.find("max_waiting_per_address")) {
    tcp.max_waiting_per_address =
        static_cast<std::size_t>(integer(*v, 1, static_cast<std::int64_t>(kMaxConnectionsLimit)));
  } else {
    tcp.max_waiting_per_address = std::min(tcp.max_waiting_per_address, tcp.max_waiting);
  }
  if (tcp.max_waiting_per_address > tcp.max_waiting) {
    fail(keys.key_mark("max_waiting_per_address"),
         value.path + ".max_waiting_per_address: " + std::to_string(tcp.max_waiting_per_address) +
             " is more than max_waiting (" + std::to_string(tcp.max_waiting) + "); lower it or raise max_waiting");
  }
  if (const auto v = keys.find("first_request_timeout_ms")) {
    tcp.first_request_timeout = duration<std::chrono::milliseconds>(*v, 100, 600000);
  }
  if (const auto v = keys.find("idle_timeout_s")) {
    tcp.idle_timeout = duration<std::chrono::seconds>(*v, 0, kMaxIdleTimeoutSeconds);
  }
  if (const auto v = keys.find("gateway_unit_id")) {
    tcp.gateway_unit_id = static_cast<std::uint8_t>(integer(*v, 1, 255));
    gateway_unit_mark_ = v->mark;
  }
  if (const auto v = keys.find("request_queue_depth")) {
    tcp.request_queue_depth = static_cast<std::size_t>(integer(*v, 1, 100000));
  }
  if (const auto v = keys.find("allow")) {
    const auto items = list(*v);
    // An empty list would lock every client out; that is never what a plant wants.
    if (items.empty()) fail(v->mark, v->path + ": empty; remove the key to let every client connect");
    for (std::size_t i = 0; i < items.size(); ++i) {
      const auto network = parse_ip_network(string(items[i]));
      if (!network) fail(items[i].mark, items[i].path + ": " + network.error());
      for (std::size_t j = 0; j < tcp.allow.size(); ++j) {
        if (tcp.allow[j] == *network) {
          fail(items[i].mark, items[i].path + ": " + network->to_string() + " is already listed as " + v->path + "[" +
                                  std::to_string(j) + "] (" + place(items[j].mark) + ")");
        }
      }
      tcp.allow.push_back(*network);
    }
  }
  if (const auto v = keys.find("plain")) tcp.plain = boolean(*v);
  if (const auto v = keys.find("tls")) tcp.tls = parse_tls(*v);
  if (!tcp.plain && !tcp.tls) {
    fail(keys.find("plain")->mark, value.path + ".plain: false leaves the gateway without a listener; configure " +
                                       value.path + ".tls (Modbus/TCP Security) or remove the key");
  }
  if (tcp.plain && tcp.tls && tcp.tls->listen == tcp.listen) {
    fail(keys.key_mark("tls"), value.path + ".tls.listen: " + tcp.listen.to_string() + " is also " + value.path +
                                   ".listen (plain Modbus TCP); give TLS its own port (802 is Modbus/TCP Security's) "
                                   "or set plain: false");
  }
  return tcp;
}

TlsConfig Loader::parse_tls(const Value& value) {
  const MapReader keys(*this, value, kTlsKeys);
  TlsConfig tls;
  tls.listen = host_port(keys.require("listen"));
  tls.certificate = string(keys.require("certificate"));
  tls.private_key = string(keys.require("private_key"));
  tls.ca = string(keys.require("ca"));
  if (const auto v = keys.find("roles")) {
    named_map(*v,
              "a map of certificate names (subject CN or subjectAltName) to roles (read, operate, engineer, "
              "none), e.g. {plc-1: operate}",
              [&](const std::string& name, const YAML::Mark&, const Value& role) {
                tls.roles.push_back(TlsRoleMapping{name, choice(role, detail::kRoleNames)});
              });
  }
  if (const auto v = keys.find("default_role")) tls.default_role = choice(*v, detail::kRoleNames);
  if (const auto v = keys.find("role_names")) {
    named_map(*v,
              "a map of role extension texts of other schemes to roles (read, operate, engineer, none), e.g. "
              "{Operator: operate}",
              [&](const std::string& name, const YAML::Mark& mark, const Value& role) {
                if (role_from_name(name)) {
                  fail(mark, v->path + ": `" + name + "` already is a role; list only other names here");
                }
                tls.role_names.push_back(TlsRoleMapping{name, choice(role, detail::kRoleNames)});
              });
  }
  if (const auto v = keys.find("handshake_timeout_ms")) {
    tls.handshake_timeout = duration<std::chrono::milliseconds>(*v, 100, 60000);
  }
  if (const auto v = keys.find("max_handshakes")) {
    tls.max_handshakes = static_cast<std::size_t>(integer(*v, 1, static_cast<std::int64_t>(kMaxConnectionsLimit)));
  }
  if (const auto v = keys.find("max_handshakes_per_address")) {
    tls.max_handshakes_per_address =
        static_cast<std::size_t>(integer(*v, 1, static_cast<std::int64_t>(kMaxConnectionsLimit)));
  }
  if (!keys.find("max_handshakes_per_address")) {
    tls.max_handshakes_per_address = std::min(tls.max_handshakes_per_address, tls.max_handshakes);
  }
  if (tls.max_handshakes_per_address > tls.max_handshakes) {
    fail(keys.key_mark("max_handshakes_per_address"),
         value.path + ".max_handshakes_per_address: " + std::to_string(tls.max_handshakes_per_address) +
             " is more than max_handshakes (" + std::to_string(tls.max_handshakes) +
             "); lower it or raise max_handshakes");
  }
  return tls;
}

// A Sparkplug ID (group, edge node, device): MQTT topic levels, so no '/', '+' or '#'.
bool valid_sparkplug_id(std::string_view id) {
  return !id.empty() && id.find_first_of("/+#") == std::string_view::npos;
}

std::optional<MqttConfig> Loader::parse_mqtt(const Value& value, const Config& config) {
  const MapReader keys(*this, value, kMqttKeys);
  // `enabled: false` keeps a section in the file without connecting (a broker not there yet).
  if (const auto v = keys.find("enabled"); v && !boolean(*v)) return std::nullopt;
  MqttConfig mqtt;
  mqtt.broker = host_port(keys.require("broker"));
  const auto id = [&](std::string_view key) {
    const Value v = keys.require(key);
    std::string text = string(v);
    if (!valid_sparkplug_id(text)) {
      fail(v.mark, v.path + ": `" + text +
                       "` cannot be a Sparkplug ID: it is an MQTT topic level, so no '/', '+' "
                       "or '#'");
    }
    return text;
  };
  mqtt.group_id = id("group_id");
  mqtt.edge_node_id = id("edge_node_id");
  if (keys.find("primary_host_id")) mqtt.primary_host_id = id("primary_host_id");
  mqtt.client_id = "sms-gateway-" + mqtt.edge_node_id;
  if (const auto v = keys.find("client_id")) mqtt.client_id = string(*v);
  if (const auto v = keys.find("username")) mqtt.username = string(*v);
  if (const auto v = keys.find("password_file")) {
    if (mqtt.username.empty())
      fail(v->mark, v->path + ": a password needs a username; add " + value.path + ".username");
    mqtt.password_file = string(*v);
  }
  if (const auto v = keys.find("tls")) {
    const MapReader tls_keys(*this, *v, kMqttTlsKeys);
    MqttTlsConfig tls;
    tls.ca = string(tls_keys.require("ca"));
    const auto certificate = tls_keys.find("certificate");
    const auto key = tls_keys.find("private_key");
    if (certificate.has_value() != key.has_value()) {
      fail(v->mark, v->path +
                        ": certificate and private_key go together (a client certificate for the broker); "
                        "give both or neither");
    }
    if (certificate) tls.certificate = string(*certificate);
    if (key) tls.private_key = string(*key);
    mqtt.tls = std::move(tls);
  }
  if (const auto v = keys.find("keepalive_s")) mqtt.keepalive = duration<std::chrono::seconds>(*v, 5, 3600);
  if (const auto v = keys.find("role")) mqtt.role = choice(*v, detail::kRoleNames);
  if (const auto v = keys.find("data_period_ms")) mqtt.data_period = duration<std::chrono::milliseconds>(*v, 10, 60000);
  if (const auto v = keys.find("report_period_s")) mqtt.report_period = duration<std::chrono::seconds>(*v, 0, 86400);
  if (const auto v = keys.find("reconnect_min_ms"))
    mqtt.reconnect_min = duration<std::chrono::milliseconds>(*v, 100, 60000);
  if (const auto v = keys.find("reconnect_max_ms")) {
    mqtt.reconnect_max = duration<std::chrono::milliseconds>(*v, 100, 3600000);
  }
  if (mqtt.reconnect_max < mqtt.reconnect_min) {
    fail(keys.key_mark("reconnect_max_ms"),
         value.path + ".reconnect_max_ms: " + std::to_string(mqtt.reconnect_max.count()) +
             " is below reconnect_min_ms (" + std::to_string(mqtt.reconnect_min.count()) + ")");
  }
  if (const auto v = keys.find("deadband")) {
    named_map(*v, "a map of field names to deadbands in register units, e.g. {present_position: 2}",
              [&](const std::string& field, const YAML::Mark& mark, const Value& band) {
                bool known = false;
                for (const auto* table : modbus_map::all_tables()) {
                  for (const auto& spec : table->fields) known = known || spec.name == field;
                }
                if (!known) {
                  fail(mark, v->path + ": `" + field +
                                 "` is not a field of any table (docs/REGISTER_MAP.md lists "
                                 "each table's fields)");
                }
                mqtt.deadbands.push_back(MqttDeadband{field, static_cast<std::uint32_t>(integer(band, 0, 65535))});
              });
  }
  // Every table servo is a device; its ID must be a topic level and unique.
  for (std::size_t i = 0; i < config.servos.size(); ++i) {
    const auto& servo = config.servos[i];
    if (servo.passthrough()) continue;
    const std::string device = sparkplug_device_id(servo);
    if (!valid_sparkplug_id(device)) {
      fail(servo_places_[i].item, servo_places_[i].path + ".name: `" + device +
                                      "` cannot be a Sparkplug device ID "
                                      "(mqtt is configured): no '/', '+' or '#'");
    }
    for (std::size_t j = 0; j < i; ++j) {
      if (!config.servos[j].passthrough() && sparkplug_device_id(config.servos[j]) == device) {
        fail(servo_places_[i].item, servo_places_[i].path + ".name: Sparkplug device ID `" + device + "` is also " +
                                        servo_places_[j].path + "'s (" + place(servo_places_[j].item) +
                                        "); names must be unique when mqtt is configured");
      }
    }
  }
  return mqtt;
}

void Loader::parse_buses(const Value& value, Config& config) {
  const auto items = list(value);
  if (items.empty()) fail(value.mark, "buses: at least one bus is needed");
  for (const auto& item : items) {
    BusPlaces places;
    BusConfig bus = parse_bus(item, places);
    for (std::size_t i = 0; i < config.buses.size(); ++i) {
      if (config.buses[i].name == bus.name) {
        fail(places.name, item.path + ".name: bus name `" + bus.name + "` is already used by " + bus_places_[i].path +
                              " (" + place(bus_places_[i].name) + ")");
      }
      if (config.buses[i].device == bus.device) {
        fail(places.device, item.path + ".device: " + bus.device + " is already the device of bus `" +
                                config.buses[i].name + "` (" + place(bus_places_[i].device) + ")");
      }
    }
    config.buses.push_back(std::move(bus));
    bus_places_.push_back(std::move(places));
  }
}

BusConfig Loader::parse_bus(const Value& value, BusPlaces& places) {
  const MapReader keys(*this, value, kBusKeys);
  places.path = value.path;
  BusConfig bus;

  const Value name = keys.require("name");
  bus.name = string(name);
  if (!valid_bus_name(bus.name)) {
    fail(name.mark, name.path + ": `" + bus.name + "` may use letters, digits, '_', '-' and '.' only");
  }
  places.name = name.mark;
  const Value device = keys.require("device");
  bus.device = string(device);
  places.device = device.mark;

  const Value protocol = keys.require("protocol");
  const auto parsed_protocol =
      protocol.node.IsScalar() ? protocol::bus_protocol_from_string(protocol.node.Scalar()) : std::nullopt;
  if (!parsed_protocol) {
    fail(protocol.mark, protocol.path + ": expected one of feetech, d55d, modbus-rtu, got " + describe(protocol.node));
  }
  bus.protocol = *parsed_protocol;
  const auto protocol_name = std::string(protocol::to_string(bus.protocol));

  const Value baud = keys.require("baud");
  bus.baud = static_cast<std::uint32_t>(integer(baud, 1, std::numeric_limits<std::uint32_t>::max()));
  const auto code = modbus_map::baud_code(bus.protocol, bus.baud);
  if (!code) {
    fail(baud.mark, baud.path + ": " + std::to_string(bus.baud) + " bit/s is not a " + protocol_name +
                        " rate; valid rates: " + modbus_map::valid_bauds_text(bus.protocol));
  }
  bus.baud_code = *code;

  if (const auto v = keys.find("parity")) bus.parity = choice(*v, detail::kParityNames);
  if (const auto v = keys.find("stop_bits")) {
    bus.stop_bits = static_cast<std::uint8_t>(integer(*v, 1, 2));
  }
  if (const auto v = keys.find("response_timeout_ms")) {
    bus.response_timeout = duration<std::chrono::milliseconds>(*v, 1, 10000);
  }
  if (const auto v = keys.find("retries")) bus.retries = static_cast<unsigned>(integer(*v, 0, 10));
  if (const auto v = keys.find("poll_period_ms")) bus.poll_period = duration<std::chrono::milliseconds>(*v, 0, 3600000);
  if (const auto v = keys.find("offline_probe_period_ms")) {
    bus.offline_probe_period = duration<std::chrono::milliseconds>(*v, 1, 3600000);
  }
  if (const auto v = keys.find("reopen_period_ms")) {
    bus.reopen_period = duration<std::chrono::milliseconds>(*v, 1, 3600000);
  }

  const auto poll_fields = keys.find("poll_fields");
  const auto poll_range = keys.find("poll_range");
  if (poll_fields && poll_range) {
    const bool range_second = keys.key_mark("poll_range").pos > keys.key_mark("poll_fields").pos;
    fail(range_second ? keys.key_mark("poll_range") : keys.key_mark("poll_fields"),
         value.path + ": give either poll_fields or poll_range, not both");
  }
  if (poll_fields) {
    const auto items = list(*poll_fields);
    if (items.empty()) {
      fail(poll_fields->mark, poll_fields->path + ": empty; remove the key to poll the table's feedback block");
    }
    for (const auto& item : items) {
      auto field = string(item);
      if (std::find(bus.poll.fields.begin(), bus.poll.fields.end(), field) != bus.poll.fields.end()) {
        fail(item.mark, item.path + ": field `" + field + "` is listed twice");
      }
      bus.poll.fields.push_back(std::move(field));
      places.poll_fields.push_back(item);
    }
  }
  if (poll_range) {
    const MapReader range(*this, *poll_range, kPollRangeKeys);
    AddressRange block;
    block.start = static_cast<std::uint16_t>(integer(range.require("start"), 0, 65535));
    const Value count = range.require("count");
    block.count = static_cast<std::uint16_t>(integer(count, 1, 65535));
    bus.poll.range = block;
    places.poll_range = count;
  }

  for (const auto key : kModbusRtuOnlyKeys) {
    if (bus.protocol != BusProtocol::ModbusRtu && keys.find(key)) {
      fail(keys.key_mark(key), value.path + ": `" + std::string(key) + "` applies to modbus-rtu buses only; bus `" +
                                   bus.name + "` is " + protocol_name);
    }
  }
  parse_rtu_line(keys, value, bus.modbus_rtu);
  if (const auto v = keys.find("byte_timeout_ms")) {
    bus.modbus_rtu.byte_timeout = duration<std::chrono::milliseconds>(*v, 1, 10000);
  }

  if (const auto v = keys.find("watchdog")) {
    const MapReader watchdog_keys(*this, *v, kWatchdogKeys);
    WatchdogConfig watchdog;
    watchdog.timeout = duration<std::chrono::milliseconds>(watchdog_keys.require("timeout_ms"), kMinWatchdogTimeoutMs,
                                                           kMaxWatchdogTimeoutMs);
    if (const auto feed = watchdog_keys.find("feed")) watchdog.feed = choice(*feed, detail::kWatchdogFeedNames);
    if (const auto action = watchdog_keys.find("action")) watchdog.action = choice(*action, detail::kStopActionNames);
    // A trip's stop waits for the transaction on the wire to end: a watchdog shorter than the
    // bus's worst transaction could not keep its promise (docs/PLC_GUIDE.md "Safety", the stop's bound).
    const auto worst = worst_transaction(bus);
    if (watchdog.timeout <= worst) {
      fail(
          watchdog_keys.require("timeout_ms").mark,
          v->path + ".timeout_ms: " + std::to_string(watchdog.timeout.count()) +
              " ms is not longer than this bus's worst transaction (a fence read and the request, " +
              std::to_string(1 + bus.retries) + " attempts each, each attempt response_timeout_ms " +
              std::to_string(bus.response_timeout.count()) +
              " + the longest frames' wire time = " + std::to_string(worst.count()) +
              " ms): a stop could wait behind one transaction longer than the watchdog itself. Give timeout_ms above " +
              std::to_string(worst.count()) + ", or lower response_timeout_ms or retries");
    }
    bus.watchdog = watchdog;
  }
  if (const auto v = keys.find("on_start")) {
    bus.on_start = choice(*v, detail::kStartActionNames);
  } else if (bus.watchdog) {
    // A bus with a watchdog is one where nothing may turn unattended: after a crash or a
    // restart, a servo left turning is stopped at start (docs/PLC_GUIDE.md "Safety", after a crash).
    bus.on_start = StartAction::Hold;
  }
  if (const auto v = keys.find("on_stop")) bus.on_stop = choice(*v, detail::kStopActionNames);
  // Checked against each servo's table where the servos are read.
  if (const auto v = keys.find("stop_deceleration"))
    bus.stop_deceleration = static_cast<std::int32_t>(integer(*v, 1, 255));
  return bus;
}

void Loader::parse_rtu_line(const MapReader& keys, const Value& value, ModbusRtuOptions& line) const {
  if (const auto v = keys.find("rs485")) line.rs485 = boolean(*v);
  if (const auto v = keys.find("rts")) line.rts = choice(*v, detail::kRtsNames);
  if (const auto v = keys.find("rts_delay_us")) {
    if (line.rts == RtsMode::None) {
      fail(keys.key_mark("rts_delay_us"), value.path + ": `rts_delay_us` needs `rts: up` or `rts: down`");
    }
    line.rts_delay = duration<std::chrono::microseconds>(*v, 0, 1000000);
  }
  if (const auto v = keys.find("frame_gap")) {
    const auto gap = v->node.IsScalar() ? parse_frame_gap(v->node.Scalar())
                                        : Expected<FrameGap>(unexpected("expected spec, 3.5chars or a time such as "
                                                                        "500us, got " +
                                                                        describe(v->node)));
    if (!gap) fail(v->mark, v->path + ": " + gap.error());
    line.frame_gap = *gap;
  }
}

// docs/CONSOLE.md "Configuration".
ConsoleConfig Loader::parse_console(const Value& value, const Config& config) {
  const MapReader keys(*this, value, kConsoleKeys);
  ConsoleConfig console;
  if (const auto v = keys.find("listen")) console.listen = host_port(*v);
  if (const auto v = keys.find("tls")) {
    console.tls = boolean(*v);
    if (console.tls && !config.modbus_tcp.tls) {
      fail(v->mark, v->path +
                        ": true needs modbus_tcp.tls (the console serves HTTPS with its certificate, key and "
                        "CA); configure Modbus/TCP Security first, or set tls: false");
    }
  }
  const auto certificate = keys.find("certificate");
  const auto key = keys.find("key");
  if (certificate) console.certificate = string(*certificate);
  if (key) console.key = string(*key);
  if (certificate && !key) {
    fail(certificate->mark,
         certificate->path + ": needs " + value.path + ".key too (the certificate's private key, PEM, unencrypted)");
  }
  if (key && !certificate) {
    fail(key->mark, key->path + ": needs " + value.path + ".certificate too (the certificate of this key, PEM)");
  }
  if (certificate && console.tls) {
    fail(certificate->mark, certificate->path +
                                ": tls: true already serves HTTPS, with modbus_tcp.tls's certificate and client "
                                "certificates; give either tls: true or certificate and key (the console's own, "
                                "for password users), not both");
  }
  if (const auto v = keys.find("insecure_http")) {
    console.insecure_http = boolean(*v);
    if (console.insecure_http && console.https()) {
      fail(v->mark, v->path + ": true, but the console serves HTTPS (" +
                        (console.tls ? std::string("tls: true") : std::string("certificate and key")) +
                        "); remove insecure_http");
    }
  }
  if (const auto v = keys.find("session_timeout_s")) {
    console.session_timeout = duration<std::chrono::seconds>(*v, 60, std::int64_t{7} * 24 * 3600);
  }
  if (const auto v = keys.find("users")) {
    std::vector<YAML::Mark> marks;
    for (const auto& item : list(*v)) {
      const MapReader user_keys(*this, item, kConsoleUserKeys);
      ConsoleUser user;
      const Value name = user_keys.require("name");
      user.name = string(name);
      if (user.name.find_first_not_of("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-") !=
              std::string::npos ||
          user.name.size() > 64) {
        fail(name.mark, name.path + ": `" + user.name + "`: a user name is 1-64 letters, digits, '.', '_' or '-'");
      }
      for (std::size_t i = 0; i < console.users.size(); ++i) {
        if (console.users[i].name == user.name) {
          fail(name.mark, name.path + ": user `" + user.name + "` is already " + v->path + "[" + std::to_string(i) +
                              "] (" + place(marks[i]) + ")");
        }
      }
      const Value role = user_keys.require("role");
      user.role = choice(role, detail::kRoleNames);
      if (user.role == Role::None) {
        fail(role.mark, role.path +
                            ": a user with role none could do nothing; give read, operate or engineer, or "
                            "remove the user");
      }
      const Value hash = user_keys.require("password_hash");
      user.password_hash = string(hash);
      if (!user.password_hash.starts_with("$argon2id$") && !user.password_hash.starts_with("$argon2i$")) {
        fail(hash.mark, hash.path +
                            ": not a password hash (expected the \"$argon2id$...\" text that `sms-gateway "
                            "hash-password` prints; never the password itself)");
      }
      console.users.push_back(std::move(user));
      marks.push_back(name.mark);
    }
  }
  if (const auto problem = console_listen_problem(console)) {
    fail(keys.key_mark("listen"), value.path + ".listen: " + *problem);
  }
  return console;
}

void Loader::parse_rtu_slaves(const Value& value, Config& config) {
  std::vector<YAML::Mark> device_marks;
  for (const auto& item : list(value)) {
    RtuSlaveConfig port = parse_rtu_slave(item, config);
    const MapReader keys(*this, item, kRtuSlaveKeys);
    const YAML::Mark device_mark = keys.require("device").mark;
    for (std::size_t i = 0; i < config.buses.size(); ++i) {
      if (config.buses[i].device == port.device) {
        fail(device_mark, item.path + ".device: " + port.device + " is the device of bus `" + config.buses[i].name +
                              "` (" + place(bus_places_[i].device) +
                              "); an upstream port needs a serial line of its own (a second adapter)");
      }
    }
    for (std::size_t i = 0; i < config.modbus_rtu_slave.size(); ++i) {
      if (config.modbus_rtu_slave[i].device == port.device) {
        fail(device_mark, item.path + ".device: " + port.device + " is already modbus_rtu_slave[" + std::to_string(i) +
                              "]'s device (" + place(device_marks[i]) + ")");
      }
    }
    config.modbus_rtu_slave.push_back(std::move(port));
    device_marks.push_back(device_mark);
  }
}

RtuSlaveConfig Loader::parse_rtu_slave(const Value& value, const Config& config) {
  const MapReader keys(*this, value, kRtuSlaveKeys);
  RtuSlaveConfig port;
  port.device = string(keys.require("device"));
  if (const auto v = keys.find("baud"))
    port.baud = static_cast<std::uint32_t>(integer(*v, kMinRtuSlaveBaud, kMaxRtuSlaveBaud));
  if (const auto v = keys.find("parity")) port.parity = choice(*v, detail::kParityNames);
  if (const auto v = keys.find("stop_bits")) port.stop_bits = static_cast<std::uint8_t>(integer(*v, 1, 2));
  parse_rtu_line(keys, value, port.line);
  if (const auto v = keys.find("units")) {
    const auto items = list(*v);
    if (items.empty()) fail(v->mark, v->path + ": empty; remove the key to serve every unit");
    for (const auto& item : items) {
      const auto unit = static_cast<std::uint8_t>(integer(item, 1, 255));
      if (std::find(port.units.begin(), port.units.end(), unit) != port.units.end()) {
        fail(item.mark, item.path + ": unit " + std::to_string(unit) + " is listed twice");
      }
      if (unit != config.modbus_tcp.gateway_unit_id && find_unit(config, unit) == nullptr) {
        std::vector<int> units;
        for (const auto& servo : config.servos) units.push_back(servo.unit_id);
        std::sort(units.begin(), units.end());
        units.push_back(config.modbus_tcp.gateway_unit_id);
        fail(item.mark, item.path + ": unit " + std::to_string(unit) + " is not configured; configured units: " +
                            join_numbers(units) + " (the last is the gateway unit)");
      }
      port.units.push_back(unit);
    }
  }
  if (const auto v = keys.find("role")) {
    port.role = choice(*v, detail::kRoleNames);
    if (port.role == Role::None) {
      fail(v->mark, v->path +
                        ": a port with role none could ask nothing; give read, operate or engineer, or remove "
                        "the port");
    }
  }
  if (const auto v = keys.find("reopen_period_ms")) {
    port.reopen_period = duration<std::chrono::milliseconds>(*v, 1, 3600000);
  }
  if (const auto v = keys.find("echo")) {
    // auto, or whether the adapter echoes as a boolean (true/yes/on, false/no/off).
    if (v->node.IsScalar() && v->node.Scalar() == "auto") {
      port.echo = RtuEcho::Auto;
    } else if (const auto echoes = v->node.IsScalar() ? parse_bool(v->node.Scalar()) : std::nullopt) {
      port.echo = *echoes ? RtuEcho::On : RtuEcho::Off;
    } else {
      fail(v->mark, v->path +
                        ": expected auto, on (the adapter hands back what the port sends) or off (it does "
                        "not), got " +
                        describe(v->node));
    }
  }
  return port;
}

void Loader::parse_servos(const Value& value, Config& config) {
  for (const auto& item : list(value)) {
    ServoPlaces places;
    ServoConfig servo = parse_servo(item, config, places);
    for (std::size_t i = 0; i < config.servos.size(); ++i) {
      const ServoConfig& other = config.servos[i];
      const ServoPlaces& other_places = servo_places_[i];
      if (other.unit_id == servo.unit_id) {
        fail(places.unit, item.path + ": unit " + std::to_string(servo.unit_id) + " is already used by " +
                              other_places.path + " (" + place(other_places.unit) + ")" +
                              (places.unit_given ? "" : "; the unit defaults to the servo id, give `unit`"));
      }
      if (other.bus_index == servo.bus_index && other.servo_id == servo.servo_id) {
        check_second_view(servo, places, other, other_places);
        if (!servo.view_of) servo.view_of = other.unit_id;  // the first unit of the servo
      }
      if (!servo.name.empty() && other.name == servo.name) {
        fail(places.item, item.path + ": name `" + servo.name + "` is already used by " + other_places.path + " (" +
                              place(other_places.item) + ")");
      }
    }
    config.servos.push_back(std::move(servo));
    servo_places_.push_back(std::move(places));
  }
}

// `servo` is a further unit of the servo `other` shows (same bus and id). Allowed as a second
// view of it (docs/OPERATIONS.md: an HMI's read-only units): what describes the servo itself
// must agree, and only one of the units may write, so two clients cannot fight over one servo.
void Loader::check_second_view(const ServoConfig& servo, const ServoPlaces& places, const ServoConfig& other,
                               const ServoPlaces& other_places) const {
  const std::string already = places.path + ": servo id " + std::to_string(servo.servo_id) + " is already on bus `" +
                              servo.bus + "` as " + other_places.path + " (unit " + std::to_string(other.unit_id) +
                              ", " + place(other_places.id) + ")";
  const auto table_text = [](const ServoConfig& s) {
    return s.table ? "table " + std::string(modbus_map::table(*s.table).name) : std::string("passthrough");
  };
  if (servo.table != other.table) {
    fail(places.id, already + " with " + table_text(other) + ", this one is " + table_text(servo) +
                        "; IDs on one bus must differ, or a second unit of the same servo must have its table");
  }
  std::string differs;
  if (servo.byte_order != other.byte_order) differs = "byte_order";
  if (servo.response_level != other.response_level) differs = "response_level";
  if (servo.safe_stop != other.safe_stop) differs = "safe_stop";
  if (servo.stop_deceleration != other.stop_deceleration) differs = "stop_deceleration";
  if (!differs.empty()) {
    fail(places.item,
         already + " with another " + differs +
             "; units of one servo must agree on byte_order, "
             "response_level, safe_stop and stop_deceleration (they describe the servo): give both the same");
  }
  if (!servo.read_only && !other.read_only) {
    fail(places.id, already +
                        "; IDs on one bus must differ, or a second unit of the same servo must be "
                        "`read_only: true` (two writable units would let two clients command one servo "
                        "against each other)");
  }
}

ServoConfig Loader::parse_servo(const Value& value, const Config& config, ServoPlaces& places) {
  const MapReader keys(*this, value, kServoKeys);
  places.item = value.mark;
  places.path = value.path;
  ServoConfig servo;

  const Value bus_value = keys.require("bus");
  servo.bus = string(bus_value);
  const auto bus_it = std::find_if(config.buses.begin(), config.buses.end(),
                                   [&](const BusConfig& bus) { return bus.name == servo.bus; });
  if (bus_it == config.buses.end()) {
    std::string names;
    for (const auto& bus : config.buses) names += (names.empty() ? "" : ", ") + bus.name;
    fail(bus_value.mark, bus_value.path + ": unknown bus `" + servo.bus + "`; configured buses: " + names);
  }
  const BusConfig& bus = *bus_it;
  servo.bus_index = static_cast<std::size_t>(bus_it - config.buses.begin());
  const auto protocol_name = std::string(protocol::to_string(bus.protocol));

  const Value table_value = keys.require("table");
  const std::string table_name = string(table_value);
  const TableSpec* table = nullptr;
  if (table_name == kPassthroughTable) {
    if (bus.protocol != BusProtocol::ModbusRtu) {
      fail(table_value.mark, table_value.path + ": passthrough forwards Modbus PDUs and needs a modbus-rtu bus; bus `" +
                                 bus.name + "` is " + protocol_name);
    }
  } else {
    const auto id = modbus_map::table_from_name(table_name);
    if (!id) {
      fail(table_value.mark, table_value.path + ": unknown table `" + table_name + "`; allowed: " + table_names_text());
    }
    table = &modbus_map::table(*id);
    if (table->protocol != bus.protocol) {
      fail(table_value.mark, table_value.path + ": table " + table_name + " is spoken on " +
                                 std::string(protocol::to_string(table->protocol)) + " buses; bus `" + bus.name +
                                 "` is " + protocol_name);
    }
    servo.table = *id;
  }

  const Value id_value = keys.require("id");
  const bool packet_bus = bus.protocol != BusProtocol::ModbusRtu;
  servo.servo_id =
      static_cast<std::uint8_t>(integer(id_value, packet_bus ? 0 : 1, packet_bus ? kMaxPacketServoId : kMaxUnitId));
  places.id = id_value.mark;

  if (const auto v = keys.find("unit")) {
    servo.unit_id = static_cast<std::uint8_t>(integer(*v, 1, kMaxUnitId));
    places.unit = v->mark;
    places.unit_given = true;
  } else {
    if (servo.servo_id < 1 || servo.servo_id > kMaxUnitId) {
      fail(id_value.mark, id_value.path + ": servo id " + std::to_string(servo.servo_id) +
                              " cannot be its unit id (units are 1..247); give `unit`");
    }
    servo.unit_id = servo.servo_id;
    places.unit = id_value.mark;
  }
  if (servo.unit_id == config.modbus_tcp.gateway_unit_id) {
    fail(places.unit, value.path + ": unit " + std::to_string(servo.unit_id) +
                          " is the gateway's own unit (modbus_tcp.gateway_unit_id" +
                          (gateway_unit_mark_ ? ", " + place(*gateway_unit_mark_) : std::string()) + ")" +
                          (places.unit_given ? "" : "; the unit defaults to the servo id, give `unit`"));
  }

  if (const auto v = keys.find("profile")) {
    if (!table) fail(v->mark, v->path + ": passthrough units have no profile; remove the key");
    servo.profile = choice(*v, detail::kProfileNames);
    if (servo.profile == Profile::Smsmb) {
      if (table->id == TableId::Smsmb) {
        servo.profile = Profile::Native;  // its native map is the SMSMB map
      } else if (table->id != TableId::Sts && table->id != TableId::Sms1) {
        fail(v->mark, v->path + ": profile smsmb shows sts and sms1 servos as SMSMB servos; this servo's table is " +
                          table_name);
      }
    }
  }

  if (const auto v = keys.find("byte_order")) {
    if (!table || table->addressing != modbus_map::Addressing::Byte) {
      fail(v->mark, v->path + ": byte_order applies to the packet tables (sts, sms1, d55d); " + table_name +
                        " registers are always high byte first");
    }
    servo.byte_order = choice(*v, detail::kByteOrderNames);
  }

  if (const auto v = keys.find("response_level")) {
    const auto* field = table ? modbus_map::field_by_name(*table, "response_level") : nullptr;
    if (!field) {
      fail(v->mark, v->path + ": " + table_name +
                        " servos have no response level (a Modbus slave answers every "
                        "unicast request)");
    }
    servo.response_level = static_cast<std::uint8_t>(integer(*v, field->min, field->max));
  }

  // A rate the protocol has may still be beyond one table's servos (docs/PROTOCOL.md §3: feetech codes 8-11
  // are sts only).
  if (table) {
    if (const auto* field = modbus_map::field_by_name(*table, "baud_rate");
        field && table->addressing == modbus_map::Addressing::Byte && bus.baud_code > field->max) {
      const auto last_rate = modbus_map::baud_from_code(bus.protocol, static_cast<std::uint8_t>(field->max));
      fail(table_value.mark, table_value.path + ": " + table_name + " servos cannot run at " +
                                 std::to_string(bus.baud) + " bit/s (bus `" + bus.name +
                                 "`): their baud table ends at code " + std::to_string(field->max) + " (" +
                                 std::to_string(last_rate.value_or(0)) + " bit/s)");
    }
  }

  if (const auto v = keys.find("read_only")) servo.read_only = boolean(*v);
  if (const auto v = keys.find("safe_stop")) {
    if (!servo.table) {
      fail(keys.key_mark("safe_stop"), value.path +
                                           ".safe_stop: a passthrough unit has no table the gateway "
                                           "could stop it with; remove the key");
    }
    servo.safe_stop = choice(*v, detail::kStopActionNames);
  }
  if (const auto v = keys.find("stop_deceleration")) {
    if (!servo.table) {
      fail(keys.key_mark("stop_deceleration"), value.path +
                                                   ".stop_deceleration: a passthrough unit has no table the gateway "
                                                   "could stop it with; remove the key");
    }
    const auto count = static_cast<std::int32_t>(integer(*v, 1, 255));
    if (const auto why = modbus_map::check_stop_deceleration(modbus_map::motion_spec(*servo.table), count)) {
      fail(v->mark, v->path + ": " + *why);
    }
    servo.stop_deceleration = count;
  } else if (servo.table && bus.stop_deceleration) {
    if (const auto why =
            modbus_map::check_stop_deceleration(modbus_map::motion_spec(*servo.table), *bus.stop_deceleration)) {
      fail(places.id, value.path + ": bus `" + bus.name + "`'s stop_deceleration " +
                          std::to_string(*bus.stop_deceleration) + " does not fit this servo: " + *why +
                          "; give the servo its own stop_deceleration, or remove the bus's");
    }
  }
  if (const auto v = keys.find("name")) servo.name = string(*v);
  return servo;
}

void Loader::check_poll_selections(const Config& config) {
  for (std::size_t b = 0; b < config.buses.size(); ++b) {
    const BusConfig& bus = config.buses[b];
    const BusPlaces& places = bus_places_[b];
    for (std::size_t s = 0; s < config.servos.size(); ++s) {
      const ServoConfig& servo = config.servos[s];
      if (servo.bus_index != b || !servo.table) continue;  // passthrough units are not polled
      const TableSpec& table = modbus_map::table(*servo.table);
      const std::string who = servo_places_[s].path + " (unit " + std::to_string(servo.unit_id) + ", table " +
                              std::string(table.name) + ")";
      for (std::size_t f = 0; f < bus.poll.fields.size(); ++f) {
        if (!modbus_map::field_by_name(table, bus.poll.fields[f])) {
          fail(places.poll_fields[f].mark, places.poll_fields[f].path + ": " + who + " has no field `" +
                                               bus.poll.fields[f] + "`; its fields: " + field_names_text(table));
        }
      }
      if (bus.poll.range) {
        const auto end = static_cast<std::uint32_t>(bus.poll.range->start) + bus.poll.range->count;
        if (end > modbus_map::end_address(table)) {
          fail(places.poll_range->mark, places.path + ".poll_range: " + std::to_string(bus.poll.range->start) + ".." +
                                            std::to_string(end - 1) + " runs past the end of " + who +
                                            ", whose last address is " +
                                            std::to_string(modbus_map::end_address(table) - 1));
        }
      }
    }
    if (bus.poll.range) {
      const bool rtu = bus.protocol == BusProtocol::ModbusRtu;
      const std::uint16_t limit = rtu ? kMaxRtuReadRegisters : kMaxPacketReadBytes;
      if (bus.poll.range->count > limit) {
        fail(places.poll_range->mark, places.path + ".poll_range.count: one read takes at most " +
                                          std::to_string(limit) + (rtu ? " registers" : " bytes") + " on a " +
                                          std::string(protocol::to_string(bus.protocol)) + " bus");
      }
    }
  }
}

void Loader::parse_sync_groups(const Value& value, Config& config) {
  for (const auto& item : list(value)) {
    const MapReader keys(*this, item, kSyncGroupKeys);
    SyncGroupConfig group = parse_sync_group(keys, config);
    const YAML::Mark name_mark = keys.require("name").mark;
    const YAML::Mark start_mark = keys.require("holding_register_start").mark;
    const auto first = group.holding_register_start;
    const auto last = first + group.register_count() - 1;
    for (std::size_t i = 0; i < config.sync_groups.size(); ++i) {
      const SyncGroupConfig& other = config.sync_groups[i];
      if (other.name == group.name) {
        fail(name_mark, item.path + ".name: sync group `" + group.name + "` is already defined as sync_groups[" +
                            std::to_string(i) + "]");
      }
      const auto other_first = other.holding_register_start;
      const auto other_last = other_first + other.register_count() - 1;
      if (first <= other_last && other_first <= last) {
        fail(start_mark, item.path + ".holding_register_start: registers " + std::to_string(first) + ".." +
                             std::to_string(last) + " overlap sync group `" + other.name + "` (" +
                             std::to_string(other_first) + ".." + std::to_string(other_last) + ", " +
                             place(group_start_marks_[i]) + ")");
      }
    }
    // The heartbeat registers (docs/PLC_GUIDE.md "Safety") are the gateway unit's too.
    const std::size_t heartbeat_last = kHeartbeatRegisterBase + config.buses.size() - 1;
    if (!config.buses.empty() && first <= heartbeat_last && kHeartbeatRegisterBase <= last) {
      fail(start_mark, item.path + ".holding_register_start: registers " + std::to_string(first) + ".." +
                           std::to_string(last) + " overlap the buses' watchdog heartbeat registers " +
                           std::to_string(kHeartbeatRegisterBase) + ".." + std::to_string(heartbeat_last) +
                           " (1000 + bus index); move the group");
    }
    config.sync_groups.push_back(std::move(group));
    group_start_marks_.push_back(start_mark);
  }
}

SyncGroupConfig Loader::parse_sync_group(const MapReader& keys, const Config& config) {
  SyncGroupConfig group;
  group.name = string(keys.require("name"));
  const Value field = keys.require("field");
  group.field = string(field);

  const Value members = keys.require("members");
  const auto items = list(members);
  if (items.empty()) fail(members.mark, members.path + ": a sync group needs at least one member unit");
  if (items.size() > kMaxWriteRegisters) {
    fail(members.mark, members.path + ": " + std::to_string(items.size()) + " members; one FC16 write takes at most " +
                           std::to_string(kMaxWriteRegisters) + " registers");
  }

  // One SYNC WRITE frame per bus carries one address and length for all its servos.
  std::map<std::size_t, std::pair<const modbus_map::FieldSpec*, std::uint8_t>> field_on_bus;
  for (const auto& item : items) {
    const auto unit = static_cast<std::uint8_t>(integer(item, 1, 255));
    if (std::find(group.members.begin(), group.members.end(), unit) != group.members.end()) {
      fail(item.mark, item.path + ": unit " + std::to_string(unit) + " is listed twice");
    }
    const auto servo_it = std::find_if(config.servos.begin(), config.servos.end(),
                                       [&](const ServoConfig& servo) { return servo.unit_id == unit; });
    if (servo_it == config.servos.end()) {
      std::vector<int> units;
      for (const auto& servo : config.servos) units.push_back(servo.unit_id);
      std::sort(units.begin(), units.end());
      fail(item.mark, item.path + ": unknown unit " + std::to_string(unit) +
                          "; configured units: " + (units.empty() ? std::string("none") : join_numbers(units)));
    }
    const ServoConfig& servo = *servo_it;
    const std::string who = "unit " + std::to_string(unit);
    if (!servo.table) fail(item.mark, item.path + ": " + who + " is a passthrough unit and has no fields to write");
    if (servo.read_only) fail(item.mark, item.path + ": " + who + " is read_only");
    const TableSpec& table = modbus_map::table(*servo.table);
    const auto* spec = modbus_map::field_by_name(table, group.field);
    if (!spec) {
      fail(field.mark, field.path + ": " + who + " (table " + std::string(table.name) + ") has no field `" +
                           group.field + "`; its fields: " + field_names_text(table));
    }
    if (spec->access == modbus_map::Access::ReadOnly) {
      fail(field.mark, field.path + ": `" + group.field + "` is read-only in table " + std::string(table.name) + " (" +
                           who + "); a sync group writes its field");
    }
    const auto [entry, inserted] = field_on_bus.try_emplace(servo.bus_index, spec, unit);
    if (!inserted && (entry->second.first->addr != spec->addr || entry->second.first->size != spec->size)) {
      fail(field.mark, field.path + ": `" + group.field + "` is at address " + std::to_string(spec->addr) + " (size " +
                           std::to_string(spec->size) + ") on " + who + " but at address " +
                           std::to_string(entry->second.first->addr) + " (size " +
                           std::to_string(entry->second.first->size) + ") on unit " +
                           std::to_string(entry->second.second) + "; members on one bus (`" + servo.bus +
                           "`) share one SYNC WRITE frame, so the field must be at one address");
    }
    group.members.push_back(unit);
  }

  if (const auto v = keys.find("move_time")) {
    group.move_time = boolean(*v);
    if (group.move_time) check_timed_move_members(*v, group, config);
  }
  if (const auto v = keys.find("stretch")) {
    group.stretch = boolean(*v);
    if (group.stretch && !group.move_time) {
      fail(v->mark, v->path + ": `stretch` stretches a move time; the group needs `move_time: true`");
    }
  }

  const Value start = keys.require("holding_register_start");
  const auto last_start = static_cast<std::int64_t>(65536 - group.register_count());
  group.holding_register_start = static_cast<std::uint16_t>(integer(start, 0, last_start));
  return group;
}

void Loader::check_timed_move_members(const Value& value, const SyncGroupConfig& group, const Config& config) {
  for (const std::uint8_t unit : group.members) {
    const ServoConfig& servo = *find_unit(config, unit);
    const TableSpec& table = modbus_map::table(*servo.table);
    const std::string who = "unit " + std::to_string(unit) + " (table " + std::string(table.name) + ")";
    const std::string_view goal = modbus_map::motion_spec(table.id).goal_position;
    if (group.field != goal) {
      fail(value.mark, value.path + ": a timed move writes goal positions, but the group writes `" + group.field +
                           "`; " + who + " has its goal in `" + std::string(goal) + "`");
    }
    if (modbus_map::timed_move_spec(table.id) == nullptr) {
      fail(value.mark, value.path + ": " + who +
                           " cannot take a timed move (modbus_map/timed_move.cpp has no "
                           "profile for its table); leave it out of the group or drop `move_time`");
    }
  }
}

LoggingConfig Loader::parse_logging(const Value& value) {
  const MapReader keys(*this, value, kLoggingKeys);
  LoggingConfig logging;
  if (const auto v = keys.find("level")) logging.level = choice(*v, detail::kLogLevelNames);
  if (const auto v = keys.find("format")) logging.format = choice(*v, detail::kLogFormatNames);
  if (const auto v = keys.find("metrics_listen")) logging.metrics_listen = host_port(*v);
  return logging;
}

// Counts documents without building them, stopping at the second: yaml-cpp 0.7's LoadAll never
// returns on some malformed input (a lone `,` yields empty documents forever, jbeder/yaml-cpp#1040).
class DocumentCounter : public YAML::EventHandler {
 public:
  void OnDocumentStart(const YAML::Mark& mark) override {
    if (++count_ == 2) second_start_ = mark;
  }
  void OnDocumentEnd() override {}
  void OnNull(const YAML::Mark&, YAML::anchor_t) override {}
  void OnAlias(const YAML::Mark&, YAML::anchor_t) override {}
  void OnScalar(const YAML::Mark&, const std::string&, YAML::anchor_t, const std::string&) override {}
  void OnSequenceStart(const YAML::Mark&, const std::string&, YAML::anchor_t, YAML::EmitterStyle::value) override {}
  void OnSequenceEnd() override {}
  void OnMapStart(const YAML::Mark&, const std::string&, YAML::anchor_t, YAML::EmitterStyle::value) override {}
  void OnMapEnd() override {}

  std::size_t count() const { return count_; }
  const YAML::Mark& second_start() const { return second_start_; }

 private:
  std::size_t count_ = 0;
  YAML::Mark second_start_ = YAML::Mark::null_mark();
};

Expected<Config, ConfigError> load_text(const std::string& text, const std::string& source) {
  std::vector<YAML::Node> documents;
  try {
    std::istringstream stream(text);
    YAML::Parser parser(stream);
    DocumentCounter counter;
    while (counter.count() < 2 && parser.HandleNextDocument(counter)) {
    }
    if (counter.count() >= 2) {
      Loader(source).fail(counter.second_start(),
                          "a second YAML document starts here; the configuration is one document");
    }
    if (counter.count() == 1) documents.push_back(YAML::Load(text));
  } catch (const Failure& failure) {
    return unexpected(failure.error);
  } catch (const YAML::Exception& error) {
    ConfigError config_error;
    config_error.file = source;
    if (!error.mark.is_null()) {
      config_error.line = static_cast<std::uint32_t>(error.mark.line + 1);
      config_error.column = static_cast<std::uint32_t>(error.mark.column + 1);
    }
    config_error.message = "YAML syntax error: " + error.msg;
    return unexpected(std::move(config_error));
  }
  if (documents.empty()) {
    return unexpected(ConfigError{source, 0, 0,
                                  "the configuration is empty; it needs at least `buses` and `servos` "
                                  "(examples: config/examples/)"});
  }
  Loader loader(source);
  try {
    return loader.load(documents.front());
  } catch (const Failure& failure) {
    return unexpected(failure.error);
  }
}

}  // namespace

std::string ConfigError::to_string() const {
  if (line == 0) return file + ": " + message;
  return file + ":" + std::to_string(line) + ":" + std::to_string(column) + ": " + message;
}

Expected<Config, ConfigError> load_config_string(std::string_view text, std::string_view source_name) {
  return load_text(std::string(text), std::string(source_name));
}

Expected<Config, ConfigError> load_config_file(const std::string& path) {
  std::error_code error;
  if (std::filesystem::is_directory(path, error)) {
    return unexpected(ConfigError{path, 0, 0, "is a directory; give the configuration file"});
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    const int saved = errno;
    return unexpected(ConfigError{path, 0, 0, std::string("cannot open: ") + std::strerror(saved)});
  }
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) {
    const int saved = errno;
    return unexpected(ConfigError{path, 0, 0, std::string("cannot read: ") + std::strerror(saved)});
  }
  return load_text(text.str(), path);
}

}  // namespace sms::config
