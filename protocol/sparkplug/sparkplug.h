#pragma once
// Sparkplug B (Eclipse Sparkplug 3.0.0) as pure functions: topics and payloads, bytes in and
// bytes out. No MQTT client, no sockets, no clock: the edge node (gateway/mqtt/sparkplug_node.h)
// decides what to send and when.
//
//   Topic topic{.group = "plant", .type = MessageType::DData, .edge_node = "gw1", .device = "arm1"};
//   Payload payload{.timestamp = now_ms, .seq = 7, .metrics = {Metric::uint16("present_position", 2048)}};
//   publish(topic_text(topic), encode(payload));
//   ...
//   const auto command = decode(received_bytes);   // Expected<Payload>: error says why
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "protocol/expected.h"
#include "protocol/packet.h"

namespace sms::sparkplug {

using protocol::Bytes;

// The topic namespace of Sparkplug B (spec §4.1.1).
inline constexpr std::string_view kNamespace = "spBv1.0";

enum class MessageType : std::uint8_t { NBirth, NDeath, DBirth, DDeath, NData, DData, NCmd, DCmd, State };
std::string_view to_string(MessageType type);  // "NBIRTH", ...

// spBv1.0/{group}/{type}/{edge_node}[/{device}]
struct Topic {
  std::string group;
  MessageType type = MessageType::NData;
  std::string edge_node;
  std::string device;  // empty for node messages
  friend bool operator==(const Topic&, const Topic&) = default;
};
std::string topic_text(const Topic& topic);
// nullopt for anything that is not a Sparkplug B node or device topic (STATE topics included).
std::optional<Topic> parse_topic(std::string_view text);
// Whether `id` may be a group, edge node or device ID: not empty, and none of the characters
// MQTT or Sparkplug reserve ('/', '+', '#'); spec §4.1.1. Printable UTF-8 is the caller's check.
bool valid_id(std::string_view id);

// Metric data types (spec §6.4.16), the ones a servo metric uses and the ones a host may send.
enum class DataType : std::uint32_t {
  Unknown = 0,
  Int8 = 1,
  Int16 = 2,
  Int32 = 3,
  Int64 = 4,
  UInt8 = 5,
  UInt16 = 6,
  UInt32 = 7,
  UInt64 = 8,
  Float = 9,
  Double = 10,
  Boolean = 11,
  String = 12,
  DateTime = 13,
  Text = 14,
};
std::string_view to_string(DataType type);

// A metric's value: integers of every width ride as int64 (signed types) or uint64 (unsigned
// ones and DateTime), as the protobuf's int_value/long_value carry them; monostate is null.
using MetricValue = std::variant<std::monostate, std::int64_t, std::uint64_t, float, double, bool, std::string>;

struct Metric {
  std::string name;
  DataType type = DataType::Unknown;
  MetricValue value;
  std::optional<std::uint64_t> timestamp;  // ms since the epoch
  std::string eng_unit;                    // property "engUnit" (births only); empty: none
  bool read_only = false;                  // property "readOnly" (births only)

  static Metric of(std::string name, DataType type, MetricValue value) {
    Metric metric;
    metric.name = std::move(name);
    metric.type = type;
    metric.value = std::move(value);
    return metric;
  }
  static Metric int16(std::string name, std::int16_t value) {
    return of(std::move(name), DataType::Int16, std::int64_t{value});
  }
  static Metric uint16(std::string name, std::uint16_t value) {
    return of(std::move(name), DataType::UInt16, std::uint64_t{value});
  }
  static Metric uint32(std::string name, std::uint32_t value) {
    return of(std::move(name), DataType::UInt32, std::uint64_t{value});
  }
  static Metric int64(std::string name, std::int64_t value) { return of(std::move(name), DataType::Int64, value); }
  static Metric uint64(std::string name, std::uint64_t value) { return of(std::move(name), DataType::UInt64, value); }
  static Metric boolean(std::string name, bool value) { return of(std::move(name), DataType::Boolean, value); }
  static Metric string(std::string name, std::string value) {
    return of(std::move(name), DataType::String, std::move(value));
  }
  bool is_null() const { return std::holds_alternative<std::monostate>(value); }
  friend bool operator==(const Metric&, const Metric&) = default;
};

struct Payload {
  std::optional<std::uint64_t> timestamp;  // ms since the epoch
  std::optional<std::uint64_t> seq;        // 0..255; absent on NDEATH
  std::vector<Metric> metrics;
  friend bool operator==(const Payload&, const Payload&) = default;
};

Bytes encode(const Payload& payload);
// The datatype a metric was born with (NBIRTH/DBIRTH), by name; Unknown for a name not born.
using BirthTypes = std::function<DataType(std::string_view name)>;
// Errors: not a protobuf Payload, a metric without a name, a value that does not fit its
// declared type. Metrics with a value of a kind we do not read (bytes, dataset, template) come
// back null with their declared type, so the caller can name them in its refusal.
// Commands SHOULD NOT carry a datatype (spec, "datatype" of a metric): a metric without one is
// read as the type `birth_types` gives its name, so an Int16 -100 in 32-bit two's complement
// is -100 and not 4294967196. Without `birth_types` (or for a name it does not know) such a
// metric keeps type Unknown and its int_value/long_value reads as UInt32/UInt64.
Expected<Payload> decode(std::span<const std::uint8_t> bytes, const BirthTypes& birth_types = {});

// Integer types: the range of values the type holds; nullopt for the others (Boolean, Float,
// String, ...). UInt64's upper end is capped at INT64_MAX (no register is that wide).
struct IntegerRange {
  std::int64_t min = 0;
  std::int64_t max = 0;
};
std::optional<IntegerRange> integer_range(DataType type);

// A metric value as an integer for a register write: integers as they are, booleans 0/1, floats
// and doubles only when they are whole numbers. nullopt for null, strings and fractions.
std::optional<std::int64_t> integer_value(const MetricValue& value);

// The bdSeq metric (spec §7.1.1; an Int64, 0..255), "Node Control/Rebirth" (§6.4.x): names
// the spec fixes.
inline constexpr std::string_view kBdSeqMetric = "bdSeq";
inline constexpr std::string_view kRebirthMetric = "Node Control/Rebirth";

// A host application's STATE (Sparkplug 3.0, "STATE"): topic spBv1.0/STATE/<host_id>, retained,
// payload the JSON object {"online": true|false, "timestamp": <ms since the epoch>}.
std::string state_topic(std::string_view host_id);
struct HostState {
  bool online = false;
  std::uint64_t timestamp = 0;
  friend bool operator==(const HostState&, const HostState&) = default;
};
// Errors say what is wrong: not a JSON object, `online` missing or not a boolean, `timestamp`
// missing or not a whole number >= 0. Other keys are allowed and skipped.
Expected<HostState> parse_host_state(std::string_view json);
std::string host_state_json(const HostState& state);  // for tests and tools

}  // namespace sms::sparkplug
