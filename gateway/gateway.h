#pragma once
// The whole gateway in one object: configuration -> one bus engine per bus -> unit router
// (servo units and the gateway unit) -> Modbus TCP server, with the io thread that runs the
// TCP side, and the upstream Modbus RTU ports (gateway/rtu_slave) in front of the same router. sms-gateway's main() and
// the in-process tests use it the same way:
//
//   sms::gateway::Gateway gateway(config);
//   gateway.start();                 // throws std::runtime_error with what to do
//   ... gateway.port() ...
//   gateway.stop();                  // graceful: in-flight answers first, then the buses
#include <chrono>
#include <cstdint>
#include <memory>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/wire_monitor.h"
#include "gateway/modbus_tcp/tcp_server.h"
#include "gateway/observability/metrics.h"

namespace sms::gateway {

// The engine settings of config.buses[bus_index]: serial line, timing, queue depth, and every
// servo of the bus with the block the poll cycle reads (the configured fields or range, else
// the table's feedback block).
BusSettings bus_settings_for(const config::Config& config, std::size_t bus_index);

// The configuration `sms-gateway --simulate` runs: one feetech bus on `device` at 1 000 000
// baud with sts servos 1-6 as units 1-6 (profile native), listening on `listen`.
config::Config simulated_config(const std::string& device, const config::HostPort& listen);
// The watchdog --simulate arms on its bus (feed: any_write; docs/PLC_GUIDE.md "Safety"): a first
// HMI writing once a second (period + worst transaction + its own timer jitter) never trips it.
inline constexpr std::chrono::milliseconds kSimulateWatchdog{3000};

class Gateway {
 public:
  explicit Gateway(config::Config config);
  ~Gateway();  // stop()
  Gateway(const Gateway&) = delete;
  Gateway& operator=(const Gateway&) = delete;

  // Starts the bus engines (a missing serial port is not fatal: that bus starts down and is
  // reopened by itself), then listens for Modbus TCP and, when logging.metrics_listen is set,
  // for /metrics and /healthz. Throws std::runtime_error when it cannot listen or a bus cannot
  // be run at all.
  void start();
  // Graceful stop, from any thread but the io thread: no new connections; requests being
  // answered finish (a write handed to a bus is completed and answered), connections close,
  // then the buses stop. After `grace` the remaining connections are closed regardless.
  void stop(std::chrono::milliseconds grace = std::chrono::seconds{5});

  // The plain Modbus TCP port; 0 when modbus_tcp.plain is false.
  std::uint16_t port() const;
  // The Modbus/TCP Security port; 0 without modbus_tcp.tls.
  std::uint16_t tls_port() const;
  // SIGHUP: loads the TLS certificate, key and CA files again (new handshakes use them; on
  // failure the old ones stay and the log says why). False when it failed or there is no TLS.
  bool reload_tls();
  const config::Config& config() const { return config_; }
  // The engine of config().buses[index] (tests, benchmarks).
  BusEngine& engine(std::size_t index);
  TcpServerStats server_stats() const;
  // Everything /metrics shows, now.
  MetricsSnapshot metrics() const;
  // The metrics endpoint's bound port; 0 when it is off.
  std::uint16_t metrics_port() const;
  // The bus monitor of config().buses[index] (docs/MONITOR.md), or of the bus named `name`;
  // nullptr before start(), or for a name no bus has.
  std::shared_ptr<WireMonitor> wire_monitor(std::size_t bus_index) const;
  std::shared_ptr<WireMonitor> wire_monitor(std::string_view bus_name) const;
  // The browser console's bound port and address ("http://127.0.0.1:8080/"); 0 / empty when it is off.
  std::uint16_t console_port() const;
  std::string console_url() const;

 private:
  class Impl;
  config::Config config_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
