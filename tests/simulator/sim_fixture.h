#pragma once
// A started simulated bus and a host port on it, for the suites of tests/simulator.
#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <memory>
#include <thread>
#include <vector>

#include "protocol/instructions.h"
#include "protocol/packet.h"
#include "simulator/simulated_bus.h"
#include "tests/simulator/host_port.h"
#include "tests/support/eventually.h"

namespace sms::simulator::testing {

using ::sms::test::eventually;

inline ServoConfig sts(std::uint8_t id, std::uint32_t baud = 1'000'000) {
  return {id, modbus_map::TableId::Sts, protocol::BusProtocol::Feetech, baud};
}
inline ServoConfig sms1(std::uint8_t id, std::uint32_t baud = 1'000'000) {
  return {id, modbus_map::TableId::Sms1, protocol::BusProtocol::Feetech, baud};
}
inline ServoConfig d55d(std::uint8_t id, std::uint32_t baud = 115'200) {
  return {id, modbus_map::TableId::D55d, protocol::BusProtocol::D55d, baud};
}
inline ServoConfig smsmb(std::uint8_t id, std::uint32_t baud = 115'200) {
  return {id, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, baud};
}

inline BusOptions quick_options(std::vector<ServoConfig> servos) {
  BusOptions options;
  options.servos = std::move(servos);
  options.timing = false;  // the suites stay fast; the timing tests switch it on
  options.reboot_time = std::chrono::milliseconds(100);
  options.seed = 1;
  return options;
}

struct Rig {
  explicit Rig(BusOptions options, std::uint32_t host_baud = 0) : bus(std::make_unique<SimulatedBus>(options)) {
    bus->start();
    host = std::make_unique<HostPort>(bus->slave_path(), host_baud != 0 ? host_baud : options.servos.front().baud);
  }
  std::unique_ptr<SimulatedBus> bus;
  std::unique_ptr<HostPort> host;
};

inline protocol::Packet status(std::uint8_t id, std::uint8_t error, Bytes params = {}) {
  return protocol::Packet{id, error, std::move(params)};
}

}  // namespace sms::simulator::testing
