#pragma once
// The gateway as a Sparkplug B edge node (docs/MQTT.md): NBIRTH/NDEATH for the
// gateway, one device per table servo with DBIRTH/DDEATH following its online state, DDATA from
// the poll cache on change (per-field deadband) and every report_period, and NCMD/DCMD writes.
//
// It is a Modbus client of the gateway's own UnitRouter: every read is the FC04/FC03/FC01 a PLC
// would send, every command the FC06/FC05 a PLC would send, through the role gate first
// (gateway/service/access_gate.h, with mqtt.role). So commands take the same path as Modbus writes: the bus queue and
// its order, the watchdog (they feed it), the e-stop latch, read-only units and fields, exceptions. Commands run one at
// a time in arrival order; a command the broker delivered is carried out even when the broker goes away meanwhile (its
// result shows in the next DBIRTH).
//
// Threading: everything runs on the io thread (the router's); the MQTT link's events are posted
// there.
#include <chrono>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/mqtt/mqtt_link.h"
#include "gateway/service/request_handler.h"
#include "gateway/service/role_policy.h"
#include "modbus_map/register_map.h"
#include "protocol/sparkplug/sparkplug.h"

namespace boost::asio {
class io_context;
}

namespace sms::gateway {

class UnitRouter;

// Device metric names that are not control-table fields.
namespace sparkplug_metric {
inline constexpr std::string_view kStatus = "Gateway/Status";  // last status byte
inline constexpr std::string_view kRepliesOk = "Gateway/Replies OK";
inline constexpr std::string_view kTimeouts = "Gateway/Timeouts";
inline constexpr std::string_view kLastCommand = "Gateway/Last Command";  // "ok: goal_position := 1000"
// Node metrics (gateway unit coils and heartbeat registers).
inline constexpr std::string_view kEStop = "Gateway/E-Stop";                      // coil 1
inline constexpr std::string_view kWatchdogTripped = "Gateway/Watchdog Tripped";  // coil 2; write false re-arms
inline constexpr std::string_view kStopsOwed = "Gateway/Safe Stops Owed";         // input register 13 (docs/SAFETY.md)
// Discrete input 4: a save of the safety state failed and none has succeeded since (docs/SAFETY.md).
inline constexpr std::string_view kStateNotPersisted = "Gateway/Safety State Not Persisted";
inline constexpr std::string_view kHeartbeatPrefix = "Gateway/Heartbeat/";  // + bus name: holding 1000 + n
inline constexpr std::string_view kVersion = "Gateway/Version";
}  // namespace sparkplug_metric

// A command's value, checked before anything is written (docs/MQTT.md, commands): of the kind
// the metric was born with (an integer type for an integer metric: a Boolean, Float or String is
// no position) and within that datatype's range (UInt16 40000 does not fit an Int16 metric; it is
// not taken as -25536). The error says what was sent and what the metric takes.
Expected<std::int64_t> command_value(const sparkplug::Metric& metric, sparkplug::DataType born_as);
// A DCMD's value for the control-table field `entry` of a device's `map`: command_value(), then
// the value check every way in shares (RegisterMap::check_write: access, range, allowed values),
// worded as the console words it. The register value to write, or why not.
Expected<std::uint16_t> device_command_value(const sparkplug::Metric& metric, const modbus_map::RegisterMap& map,
                                             const modbus_map::RegisterEntry& entry);

// The files `mqtt` names, read as the node will read them: the password (first line of
// password_file; empty without one) and the TLS files. Throws std::runtime_error naming the key,
// the file and what to do. sms-gateway --check-config runs it too.
std::string read_mqtt_files(const config::MqttConfig& mqtt);

class SparkplugNode {
 public:
  // `router` answers the node's requests on `io`'s thread, `policy` holds the rights of
  // mqtt.role; all three outlive the node.
  SparkplugNode(const config::Config& config, boost::asio::io_context& io, UnitRouter& router,
                const RolePolicy& policy);
  ~SparkplugNode();
  SparkplugNode(const SparkplugNode&) = delete;
  SparkplugNode& operator=(const SparkplugNode&) = delete;

  // Reads the password file and starts the MQTT link (which retries by itself while the broker
  // is down). Throws std::runtime_error saying which file or setting is wrong.
  void start();
  // From any thread but the io thread, before the io thread stops: NDEATH, DISCONNECT, and no
  // more publishing. Idempotent. Destroy the node before its io_context (its timer lives there).
  void stop();

  SparkplugStats stats() const;  // thread-safe

  class Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

}  // namespace sms::gateway
