// monitor_capture PROTOCOL OUT.pcapng: runs the gateway in-process over the project's simulator
// on a pty (one servo, ID 1: sts for feetech, d55d, smsmb for modbus-rtu), writes the servo's
// goal position once through Modbus TCP, waits until the bus monitor holds that write and its
// answer, and saves the monitor's capture (WireMonitor::pcapng) to OUT. tshark_test.sh reads it.
// Exit status 0 when the capture was written, 1 otherwise (with the reason on stderr).
#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <thread>

#include "config/load.h"
#include "gateway/bus/wire_monitor.h"
#include "gateway/gateway.h"
#include "modbus_map/tables.h"
#include "simulator/simulated_bus.h"
#include "tests/support/modbus_client.h"

namespace {

using namespace std::chrono_literals;
using namespace sms;

struct Kind {
  std::string protocol;  // the config's spelling
  modbus_map::TableId table;
  protocol::BusProtocol bus_protocol;
  std::uint32_t baud;
  int goal_address;  // the unit's holding register of goal_position
  std::uint16_t goal;
};

int run(const Kind& kind, const std::string& out_path) {
  simulator::BusOptions options;
  options.servos = {{1, kind.table, kind.bus_protocol, kind.baud}};
  options.timing = false;
  options.seed = 1;
  simulator::SimulatedBus bus(options);
  bus.start();
  const std::string yaml =
      "modbus_tcp: {listen: \"127.0.0.1:0\"}\n"
      "buses:\n"
      "  - {name: cell, device: \"" +
      bus.slave_path() + "\", protocol: " + kind.protocol + ", baud: " + std::to_string(kind.baud) +
      ", response_timeout_ms: 100, poll_period_ms: 50, offline_probe_period_ms: 100}\n"
      "servos:\n"
      "  - {unit: 1, bus: cell, id: 1, table: " +
      std::string(modbus_map::table(kind.table).name) + "}\n";
  auto config = config::load_config_string(yaml, "<monitor_capture>");
  if (!config) {
    std::cerr << config.error().to_string() << "\n";
    return 1;
  }
  gateway::Gateway gateway(std::move(*config));
  gateway.start();
  const auto deadline = std::chrono::steady_clock::now() + 10s;
  while (!gateway.engine(0).discovered() && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(5ms);
  const auto monitor = gateway.wire_monitor(0);
  gateway::MonitorReader reader(monitor);
  {
    sms::test::ModbusClient client(gateway.port(), 1);
    const auto written = client.write_register(kind.goal_address, kind.goal);
    if (!written.ok()) {
      std::cerr << "monitor_capture: the write of goal_position was refused (exception " << written.exception << ")\n";
      return 1;
    }
  }
  // The write and its answer are on the monitor: then the capture holds them.
  bool write_seen = false;
  bool answer_seen = false;
  while (!(write_seen && answer_seen) && std::chrono::steady_clock::now() < deadline) {
    for (const auto& monitored : reader.poll(4096).frames) {
      const auto& frame = monitored.frame;
      const bool is_write = frame.servo == 1 && !frame.fields.empty() && frame.fields.front().name == "goal_position";
      if (frame.kind == modbus_map::FrameKind::Request && is_write) write_seen = true;
      if (write_seen && frame.kind == modbus_map::FrameKind::Answer && frame.servo == 1) answer_seen = true;
    }
    std::this_thread::sleep_for(5ms);
  }
  if (!(write_seen && answer_seen)) {
    std::cerr << "monitor_capture: the write and its answer never showed on the monitor\n";
    return 1;
  }
  const auto capture = monitor->pcapng();
  std::ofstream out(out_path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(capture.data()), static_cast<std::streamsize>(capture.size()));
  if (!out) {
    std::cerr << "monitor_capture: cannot write " << out_path << "\n";
    return 1;
  }
  gateway.stop();
  bus.stop();
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 3) {
    std::cerr << "usage: monitor_capture feetech|d55d|modbus-rtu OUT.pcapng\n";
    return 2;
  }
  spdlog::set_level(spdlog::level::warn);
  const std::string protocol = argv[1];
  if (protocol == "feetech")
    return run({"feetech", modbus_map::TableId::Sts, protocol::BusProtocol::Feetech, 1'000'000, 42, 3000}, argv[2]);
  if (protocol == "d55d")
    return run({"d55d", modbus_map::TableId::D55d, protocol::BusProtocol::D55d, 115'200, 30, 900}, argv[2]);
  if (protocol == "modbus-rtu") {
    return run({"modbus-rtu", modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 115'200, 0x80, 3000},
               argv[2]);
  }
  std::cerr << "monitor_capture: unknown protocol '" << protocol << "'\n";
  return 2;
}
