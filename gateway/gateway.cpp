#include "gateway/gateway.h"

#include <future>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

#include <spdlog/spdlog.h>

#include "config/load.h"
#include "gateway/console/console_server.h"
#include "gateway/modbus_tcp/tcp_serving.h"
#include "gateway/modbus_tcp/tls.h"
#include "gateway/mqtt/sparkplug_node.h"
#include "gateway/observability/metrics_server.h"
#include "gateway/rtu_slave/rtu_slave_port.h"
#include "gateway/service/role_policy.h"
#include "gateway/service/unit_catalog.h"
#include "gateway/units/safety.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

namespace {

AddressBlock poll_block_for(const config::BusConfig& bus, const config::ServoConfig& servo) {
  const auto range = poll_block_of(bus, servo);
  if (!range) throw std::runtime_error(range.error());
  return AddressBlock{range->address, range->count};
}

}  // namespace

BusSettings bus_settings_for(const config::Config& config, std::size_t bus_index) {
  const config::BusConfig& bus = config.buses.at(bus_index);
  BusSettings settings;
  settings.name = bus.name;
  settings.protocol = bus.protocol;
  settings.serial.device = bus.device;
  settings.serial.baud = bus.baud;
  settings.serial.parity = bus.parity;  // one type from the configuration down to termios2
  settings.serial.stop_bits = bus.stop_bits;
  settings.response_timeout = bus.response_timeout;
  settings.retries = bus.retries;
  settings.poll_period = bus.poll_period;
  settings.probe_period = config::effective_probe_period(bus);  // d55d: inside the motors' heartbeat
  settings.reopen_period = bus.reopen_period;
  settings.queue_depth = config.modbus_tcp.request_queue_depth;
  for (const auto& servo : config.servos) {
    if (servo.bus_index != bus_index || servo.passthrough() || servo.view_of) continue;  // polled once
    settings.servos.push_back(
        ServoSettings{servo.servo_id, *servo.table, config::effective_byte_order(servo), poll_block_for(bus, servo)});
  }
  return settings;
}

config::Config simulated_config(const std::string& device, const config::HostPort& listen) {
  // Written as YAML and loaded, so the embedded default passes the same validation as a file.
  std::string yaml = "modbus_tcp:\n  listen: \"" + listen.to_string() +
                     "\"\n"
                     "buses:\n"
                     "  - name: sim\n"
                     "    device: \"" +
                     device +
                     "\"\n"
                     "    protocol: feetech\n"
                     "    baud: 1000000\n"
                     // A demonstration that moves motors: its watchdog is armed (docs/PLC_GUIDE.md "Safety").
                     "    watchdog: {timeout_ms: " +
                     std::to_string(kSimulateWatchdog.count()) +
                     ", feed: any_write}\n"
                     "servos:\n";
  for (int id = 1; id <= 6; ++id) {
    yaml += "  - {unit: " + std::to_string(id) + ", bus: sim, id: " + std::to_string(id) + ", table: sts}\n";
  }
  // The six goal positions as holding registers 0-5 of the gateway unit: one SYNC WRITE frame;
  // register 6 the move time of a timed move (docs/PLC_GUIDE.md "Timed group moves").
  yaml +=
      "sync_groups:\n"
      "  - {name: goal_position, field: goal_position, members: [1, 2, 3, 4, 5, 6], holding_register_start: 0,\n"
      "     move_time: true}\n";
  auto config = config::load_config_string(yaml, "<--simulate>");
  if (!config)
    throw std::logic_error("the built-in --simulate configuration is invalid: " + config.error().to_string());
  return std::move(*config);
}

class Gateway::Impl {
 public:
  explicit Impl(const config::Config& config) : config_(config) {}

  ~Impl() { stop(std::chrono::seconds{5}); }

  void start() {
    if (started_) throw std::logic_error("Gateway::start called twice");
    started_ = true;
    for (std::size_t i = 0; i < config_.buses.size(); ++i) {
      gates_.push_back(std::make_shared<MotionGate>());
      try {
        BusSettings settings = bus_settings_for(config_, i);
        settings.motion_gate = gates_.back();
        monitors_.push_back(WireMonitor::for_bus(settings));
        settings.wire_monitor = monitors_.back();
        engines_.push_back(make_bus_engine(std::move(settings), config_.buses[i].modbus_rtu));
      } catch (const std::invalid_argument& error) {
        throw std::runtime_error("bus '" + config_.buses[i].name + "' (" +
                                 std::string(protocol::to_string(config_.buses[i].protocol)) +
                                 ") cannot be run: " + error.what());
      }
    }
    std::vector<BusEngine*> engines;
    for (const auto& engine : engines_) engines.push_back(engine.get());
    safety_ = std::make_unique<SafetySupervisor>(config_, engines, gates_);
    // Every unit's register map, built once; the one role policy every way in checks.
    catalog_ = std::make_unique<UnitCatalog>(config_);
    policy_ = std::make_unique<RolePolicy>(config_, *catalog_);
    router_ = std::make_unique<UnitRouter>(
        config_, *catalog_, engines, [this](std::function<void()> work) { serving_.post(std::move(work)); }, *safety_);

    TcpServerOptions options;
    options.host = config_.modbus_tcp.listen.host;
    options.port = config_.modbus_tcp.listen.port;
    options.max_connections = config_.modbus_tcp.max_connections;
    options.max_waiting = config_.modbus_tcp.max_waiting;
    options.max_waiting_per_address = config_.modbus_tcp.max_waiting_per_address;
    options.first_request_timeout = config_.modbus_tcp.first_request_timeout;
    options.idle_timeout = config_.modbus_tcp.idle_timeout;
    options.allow = config_.modbus_tcp.allow;
    options.traffic = &traffic_;
    // Listen before the buses start, so a port in use fails before any serial port is touched;
    // connections wait in the backlog until the io thread runs.
    if (config_.modbus_tcp.plain) {
      plain_index_ = serving_.listen(options, *router_);
    } else {
      spdlog::info("modbus tcp: plain Modbus TCP is off (modbus_tcp.plain: false); only Modbus/TCP Security serves");
    }
    if (const auto& tls = config_.modbus_tcp.tls) {
      try {
        tls_ = std::make_unique<TlsService>(*tls, *policy_, *router_);
      } catch (const std::exception& error) {
        throw std::runtime_error(std::string("cannot set up Modbus/TCP Security: ") + error.what());
      }
      TcpServerOptions secure = options;
      secure.host = tls->listen.host;
      secure.port = tls->listen.port;
      secure.tls = tls_.get();
      tls_index_ = serving_.listen(secure, *router_);
    }
    // Before the metrics endpoint, whose thread reads the node's counters.
    if (config_.mqtt) {
      sparkplug_ = std::make_unique<SparkplugNode>(config_, serving_.io(), *router_, *policy_);
      sparkplug_->start();  // throws for an unreadable password or TLS file; the broker may be down
    }
    // Upstream Modbus RTU ports: the same router behind each port's role (docs/RTU_PANELS.md).
    // Made before the metrics endpoint, whose thread reads their counters; started with the buses.
    for (const auto& port : config_.modbus_rtu_slave) {
      rtu_slaves_.push_back(std::make_unique<RtuSlavePort>(
          port, config_, *router_, *policy_, [this](std::function<void()> work) { serving_.post(std::move(work)); }));
    }
    // The browser console (docs/CONSOLE.md): its own thread, a Modbus client of the router.
    if (config_.console) {
      console_ = std::make_unique<console::ConsoleServer>(
          *config_.console,
          console::ConsoleBackend{
              &config_, router_.get(), router_.get(),
              [this](std::function<void()> work) { serving_.post(std::move(work)); }, [this] { return metrics(); },
              [this](std::string_view bus) { return wire_monitor_named(bus); },
              console::BusLending{[this](std::size_t bus, const std::string& who) { return lend_bus(bus, who); },
                                  [this](std::size_t bus, const std::string& who) { return take_back_bus(bus, who); },
                                  [this](std::size_t bus) { return engines_.at(bus)->line_lent(); }},
              safety_.get(), policy_.get()});
      console_->start();
    }
    if (config_.logging.metrics_listen) {
      metrics_server_ = std::make_unique<MetricsServer>(MetricsServerOptions{.listen = *config_.logging.metrics_listen},
                                                        [this] { return metrics(); });
      metrics_server_->start();
    }
    for (const auto& engine : engines_) engine->start();
    safety_->start();
    for (const auto& port : rtu_slaves_) port->start();
    serving_.run();
  }

  MetricsSnapshot metrics() const {
    std::vector<BusEngine*> engines;
    for (const auto& engine : engines_) engines.push_back(engine.get());
    MetricsSnapshot snapshot;
    if (!safety_) {
      snapshot = collect_metrics(config_, engines, server_stats(), traffic_, started_at_);
    } else {
      const SafetyFacts safety = safety_->facts();
      snapshot = collect_metrics(config_, engines, server_stats(), traffic_, started_at_, SteadyClock::now(), &safety);
    }
    if (tls_) snapshot.tls = tls_->stats();
    if (sparkplug_) snapshot.mqtt = sparkplug_->stats();
    for (const auto& port : rtu_slaves_) snapshot.rtu_slaves.push_back(port->stats());
    for (auto& [listener, door] : serving_.doors()) snapshot.listeners.push_back({listener, door});
    if (console_) snapshot.listeners.push_back({"console", console_->door_stats()});
    for (std::size_t i = 0; i < snapshot.buses.size() && i < monitors_.size(); ++i) {
      snapshot.buses[i].monitor_dropped = monitors_[i]->dropped_total();
    }
    if (console_) {
      const console::LoginStats logins = console_->login_stats();
      snapshot.console_logins = ConsoleLoginMetrics{
          logins.ok, logins.failed, logins.throttled, logins.busy, logins.addresses_waiting, logins.users_waiting};
    }
    return snapshot;
  }

  std::uint16_t metrics_port() const { return metrics_server_ ? metrics_server_->port() : 0; }
  std::uint16_t console_port() const { return console_ ? console_->port() : 0; }
  std::string console_url() const { return console_ ? console_->url() : std::string(); }

  void stop(std::chrono::milliseconds grace) {
    if (!started_ || stopped_) return;
    stopped_ = true;
    // Monitoring goes first: it reads the buses, which stop below.
    if (metrics_server_) metrics_server_->stop();
    // The console next: a hold-to-run move still held is stopped through the router, which still serves.
    if (console_) console_->stop();
    // The node says goodbye (NDEATH) and takes no more commands.
    if (sparkplug_) sparkplug_->stop();
    // The RTU ports take no new request; the one each is answering finishes first.
    for (const auto& port : rtu_slaves_) port->stop(grace);
    serving_.drain(grace);
    // The servos get their on_stop action while the buses still run (docs/PLC_GUIDE.md "Safety").
    if (safety_) safety_->stop_for_shutdown(kOnStopBound);
    for (const auto& engine : engines_) engine->stop();
    serving_.stop();
    // The io thread has ended; the node's timer must go before the io_context it was made on.
    sparkplug_.reset();
  }

  std::uint16_t port() const { return plain_index_ ? serving_.port(*plain_index_) : 0; }
  std::uint16_t tls_port() const { return tls_index_ ? serving_.port(*tls_index_) : 0; }
  bool reload_tls() {
    if (!tls_) {
      spdlog::info("SIGHUP: nothing to reload (no modbus_tcp.tls)");
      return false;
    }
    return tls_->reload();
  }
  BusEngine& engine(std::size_t index) { return *engines_.at(index); }
  std::shared_ptr<WireMonitor> wire_monitor(std::size_t index) const {
    return index < monitors_.size() ? monitors_[index] : nullptr;
  }
  std::shared_ptr<WireMonitor> wire_monitor_named(std::string_view bus_name) const {
    for (std::size_t i = 0; i < config_.buses.size(); ++i) {
      if (config_.buses[i].name == bus_name) return wire_monitor(i);
    }
    return nullptr;
  }
  TcpServerStats server_stats() const { return serving_.stats(); }

  // The console's commissioning borrows a running bus's line (docs/CONSOLE.md "Commissioning a
  // running bus's line"): first every servo of the bus gets its safe stop and motion on the bus is
  // refused, then the engine closes the port. Blocks: the console calls it on its worker thread.
  Expected<std::string> lend_bus(std::size_t index, const std::string& who) {
    BusEngine& engine = *engines_.at(index);
    const config::BusConfig& bus = config_.buses.at(index);
    if (engine.line_lent()) return "bus " + bus.name + " is stopped already; " + bus.device + " is free";
    auto stop_sent = std::make_shared<std::promise<bool>>();
    auto sent = stop_sent->get_future();
    safety_->lend_bus(index, who, [stop_sent](bool ok) { stop_sent->set_value(ok); });
    if (sent.wait_for(kLendBound) != std::future_status::ready) {
      spdlog::warn("bus {}: the safe stop before lending the line took longer than {} ms", bus.name,
                   kLendBound.count());
    }
    if (!engine.lend_line("stopped by " + who + " to commission its line (start it again from the console)",
                          kLendBound)) {
      return unexpected("bus " + bus.name + " did not close " + bus.device + " within " +
                        std::to_string(kLendBound.count()) +
                        " ms; motion on it is refused: look at the overview, then stop it again or start it");
    }
    std::string summary = "bus " + bus.name + " stopped: its servos took their safe stop, motion writes to it are " +
                          "refused and " + bus.device + " is free for commissioning";
    if (const auto owed = engine.owed_stop_count(); owed > 0) {
      summary += "; " + std::to_string(owed) +
                 " servo(s) did not answer: their safe stop is owed and sent first when the bus starts again";
    }
    return summary;
  }

  Expected<std::string> take_back_bus(std::size_t index, const std::string& who) {
    const config::BusConfig& bus = config_.buses.at(index);
    if (!engines_.at(index)->take_back_line()) {
      return unexpected("bus " + bus.name + " is not stopped for commissioning: nothing to start");
    }
    safety_->return_bus(index, who);
    return "bus " + bus.name + " started again: " + bus.device +
           " reopened, its servos are found again and motion writes are accepted";
  }

 private:
  // How long lending a bus's line waits for the safe stop's frames, and then for the port to close.
  static constexpr std::chrono::milliseconds kLendBound{5000};
  const config::Config& config_;
  const SteadyClock::time_point started_at_ = SteadyClock::now();
  ModbusTrafficCounters traffic_;
  std::unique_ptr<MetricsServer> metrics_server_;
  // How long SIGTERM waits for the on_stop frames before it lets go of the buses regardless.
  static constexpr std::chrono::milliseconds kOnStopBound{2000};
  std::vector<std::shared_ptr<MotionGate>> gates_;
  std::vector<std::shared_ptr<WireMonitor>> monitors_;  // one per bus, in configuration order
  std::vector<std::unique_ptr<BusEngine>> engines_;
  std::unique_ptr<SafetySupervisor> safety_;  // before the router, which holds a reference
  std::unique_ptr<UnitCatalog> catalog_;      // before the router and the policy, which hold references
  std::unique_ptr<RolePolicy> policy_;        // before every way in that checks it
  std::unique_ptr<UnitRouter> router_;
  std::unique_ptr<TlsService> tls_;                  // after the router it holds, before the sessions that use it
  std::unique_ptr<console::ConsoleServer> console_;  // after the router it asks; stopped first
  std::unique_ptr<SparkplugNode> sparkplug_;         // after the router it asks; its callbacks end with the io thread
  std::vector<std::unique_ptr<RtuSlavePort>> rtu_slaves_;  // after the router and policy they use
  std::optional<std::size_t> plain_index_;
  std::optional<std::size_t> tls_index_;
  TcpServing serving_;  // last: destroyed first, so no connection outlives the router
  bool started_ = false;
  bool stopped_ = false;
};

Gateway::Gateway(config::Config config) : config_(std::move(config)), impl_(std::make_unique<Impl>(config_)) {}
Gateway::~Gateway() = default;

void Gateway::start() { impl_->start(); }
void Gateway::stop(std::chrono::milliseconds grace) { impl_->stop(grace); }
std::uint16_t Gateway::port() const { return impl_->port(); }
std::uint16_t Gateway::tls_port() const { return impl_->tls_port(); }
bool Gateway::reload_tls() { return impl_->reload_tls(); }
BusEngine& Gateway::engine(std::size_t index) { return impl_->engine(index); }
TcpServerStats Gateway::server_stats() const { return impl_->server_stats(); }
MetricsSnapshot Gateway::metrics() const { return impl_->metrics(); }
std::uint16_t Gateway::metrics_port() const { return impl_->metrics_port(); }
std::shared_ptr<WireMonitor> Gateway::wire_monitor(std::size_t bus_index) const {
  return impl_->wire_monitor(bus_index);
}
std::shared_ptr<WireMonitor> Gateway::wire_monitor(std::string_view bus_name) const {
  return impl_->wire_monitor_named(bus_name);
}
std::uint16_t Gateway::console_port() const { return impl_->console_port(); }
std::string Gateway::console_url() const { return impl_->console_url(); }

}  // namespace sms::gateway
