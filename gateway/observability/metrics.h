#pragma once
// The gateway's counters as Prometheus text (exposition format 0.0.4) and its health, for the
// HTTP endpoint in metrics_server.h. Three steps, each testable alone:
//
//   ModbusTrafficCounters traffic;            // the TCP sessions count requests and answers
//   MetricsSnapshot snapshot = collect_metrics(config, engines, server.stats(), traffic, start);
//   std::string text = render_prometheus(snapshot);
//   Health health = health_of(snapshot);      // /healthz
//
// Collecting reads atomics and takes each bus's cache mutex for a copy, like a Modbus read of
// the gateway unit does: it never waits for a bus.
#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_counters.h"
#include "gateway/bus/poll_cache.h"
#include "gateway/modbus_tcp/tcp_server.h"
#include "gateway/modbus_tcp/tls_stats.h"
#include "gateway/modbus_tcp/traffic_counters.h"
#include "gateway/mqtt/mqtt_stats.h"
#include "gateway/rtu_slave/rtu_slave_stats.h"
#include "gateway/units/safety.h"

namespace sms::gateway {

class BusEngine;

struct ServoMetrics {
  std::uint8_t unit_id = 0;
  std::uint8_t servo_id = 0;
  std::string name;  // servos[].name, may be empty
  bool online = false;
  OfflineReason offline_reason = OfflineReason::None;
  std::optional<std::chrono::microseconds> cache_age;  // nullopt: never polled successfully
  ServoCountersSnapshot counters;
};

struct BusMetrics {
  std::string name;
  std::string protocol;  // feetech, d55d, modbus-rtu
  bool up = false;
  BusCountersSnapshot counters;
  std::size_t servos_online = 0;
  std::vector<ServoMetrics> servos;      // the polled servos, in configuration order
  std::optional<BusSafetyFacts> safety;  // docs/PLC_GUIDE.md "Safety"; empty where no supervisor runs
  // Bus monitor records its readers missed (docs/MONITOR.md); empty where the bus has no monitor.
  std::optional<std::uint64_t> monitor_dropped;
};

// One TCP listener's front door (gateway/net/door.h), as sms_gateway_listener_* show it.
struct ListenerDoor {
  std::string listener;  // "plain", "tls", "console", "metrics"
  DoorStats door;
};

// The browser console's password logins (docs/CONSOLE.md "Logins").
struct ConsoleLoginMetrics {
  std::uint64_t ok = 0;
  std::uint64_t failed = 0;     // wrong password or unknown user
  std::uint64_t throttled = 0;  // refused at once: the address or the user waits after failures
  std::uint64_t busy = 0;       // refused at once: the queue of password checks was full
  std::uint64_t addresses_waiting = 0;
  std::uint64_t users_waiting = 0;
};

struct MetricsSnapshot {
  std::string version;  // SMS_GATEWAY_VERSION
  std::chrono::seconds uptime{0};
  std::vector<BusMetrics> buses;
  TcpServerStats tcp;
  std::optional<TlsStats> tls;         // empty without modbus_tcp.tls
  std::optional<SparkplugStats> mqtt;  // empty without mqtt
  ModbusTrafficSnapshot traffic;
  bool estop_latched = false;
  std::uint64_t estops = 0;
  // A save of the safety state to state_dir failed and none has succeeded since (docs/SAFETY.md).
  bool safety_state_not_persisted = false;
  std::string safety_state_problem;
  std::vector<RtuSlaveStats> rtu_slaves;              // the upstream Modbus RTU ports, in configuration order
  std::optional<ConsoleLoginMetrics> console_logins;  // empty without the browser console
  std::vector<ListenerDoor> listeners;                // every TCP listener's door
};

// One bus of `config` as its cache and counters show it at `now`. Servos of the bus that the
// cache does not hold (passthrough units) are left out.
BusMetrics read_bus_metrics(const config::Config& config, std::size_t bus_index, bool up,
                            const BusCountersSnapshot& counters, const PollCache& cache, SteadyClock::time_point now);

// Everything, from the running parts. `engines[i]` runs config.buses[i].
// `safety`: the supervisor's facts, when one runs.
MetricsSnapshot collect_metrics(const config::Config& config, std::span<BusEngine* const> engines,
                                const TcpServerStats& tcp, const ModbusTrafficCounters& traffic,
                                SteadyClock::time_point started, SteadyClock::time_point now = SteadyClock::now(),
                                const SafetyFacts* safety = nullptr);

// Prometheus text exposition format 0.0.4: "# HELP" and "# TYPE" for every family, then its
// samples; one trailing newline. Names and units in docs/DECISIONS.md "Operations and security".
std::string render_prometheus(const MetricsSnapshot& snapshot);

inline constexpr std::string_view kPrometheusContentType = "text/plain; version=0.0.4; charset=utf-8";

struct Health {
  bool ok = true;
  std::string reason;  // "ok", or what is wrong: "bus arm is down; bus base is down"
};
// Healthy when every bus is up and the safety state is persisted.
Health health_of(const MetricsSnapshot& snapshot);

}  // namespace sms::gateway
