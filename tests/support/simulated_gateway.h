#pragma once
// The whole gateway in-process over a simulated bus on a real pty: SimulatedBus (the servos),
// Gateway (engines, router, TCP server on an ephemeral loopback port) and libmodbus clients.
// Nothing is mocked: requests cross a TCP socket, frames cross the pty.
#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>

#include "config/load.h"
#include "gateway/gateway.h"
#include "simulator/simulated_bus.h"
#include "tests/support/eventually.h"
#include "tests/support/modbus_client.h"
#include "tests/support/processes.h"

namespace sms::gateway::testing {

using namespace std::chrono_literals;
using test::eventually;
using test::ModbusClient;

inline simulator::BusOptions untimed_bus(std::vector<simulator::ServoConfig> servos) {
  simulator::BusOptions options;
  options.servos = std::move(servos);
  options.timing = false;  // answers at once: these tests are about behaviour, not wire time
  options.seed = 1;
  return options;
}

inline simulator::BusOptions sts_bus(int count) {
  std::vector<simulator::ServoConfig> servos;
  for (int id = 1; id <= count; ++id) servos.push_back({static_cast<std::uint8_t>(id)});
  return untimed_bus(std::move(servos));
}

// `yaml` is a whole configuration in which "@DEVICE@" stands for the simulated bus's pty and
// "@LISTEN@" for an ephemeral loopback port.
class SimulatedGateway {
 public:
  // `prepare` runs on the started simulator before the gateway starts (and discovers it).
  SimulatedGateway(simulator::BusOptions bus_options, const std::string& yaml,
                   const std::function<void(simulator::SimulatedBus&)>& prepare = {})
      : bus_(std::move(bus_options)) {
    bus_.start();
    if (prepare) prepare(bus_);
    std::string text = yaml;
    replace(text, "@DEVICE@", bus_.slave_path());
    replace(text, "@LISTEN@", "127.0.0.1:0");
    auto config = config::load_config_string(text, "<test>");
    if (!config) throw std::runtime_error(config.error().to_string());
    gateway_.emplace(std::move(*config));
    gateway_->start();
  }
  ~SimulatedGateway() {
    gateway_.reset();
    bus_.stop();
  }

  simulator::SimulatedBus& bus() { return bus_; }
  Gateway& gateway() { return *gateway_; }
  std::uint16_t port() const { return gateway_->port(); }

  // Waits until the bus engine has discovered its servos and polled the cache once for `unit`
  // (its cache-age register stops saying "never").
  void wait_until_polled(int unit) { test::wait_until_polled(port(), unit); }

 private:
  static void replace(std::string& text, const std::string& what, const std::string& with) {
    for (std::size_t at; (at = text.find(what)) != std::string::npos;) text.replace(at, what.size(), with);
  }

  simulator::SimulatedBus bus_;
  std::optional<Gateway> gateway_;
};

// Six sts servos, units 1-6, a sync group of their goal positions at holding 0-5 of unit 255.
inline const char* const kSixStsConfig = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: arm, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sts}
  - {unit: 3, bus: arm, id: 3, table: sts, profile: smsmb}
  - {unit: 4, bus: arm, id: 4, table: sts}
  - {unit: 5, bus: arm, id: 5, table: sts}
  - {unit: 6, bus: arm, id: 6, table: sts}
sync_groups:
  - {name: goals, field: goal_position, members: [1, 2, 3, 4, 5, 6], holding_register_start: 0}
)";

}  // namespace sms::gateway::testing
