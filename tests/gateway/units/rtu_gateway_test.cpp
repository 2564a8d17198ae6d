// A modbus-rtu bus of SMSMB servos through the docs/PLC_GUIDE.md contract: a configuration ->
// Gateway (RtuBusEngine -> UnitRouter -> Modbus TCP server),
// with libmodbus TCP clients, against the simulator's SMSMB servos on a pty. The native
// profile of an smsmb unit is the SMSMB register map itself (docs/PROTOCOL.md §2.4).
#include <gtest/gtest.h>
#include <modbus/modbus.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "config/load.h"
#include "gateway/gateway.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using testing::eventually;

// The whole gateway (gateway.h) on a configuration with a modbus-rtu bus.
class RtuGateway {
 public:
  explicit RtuGateway(const std::string& yaml) : gateway_(load(yaml)) { gateway_.start(); }
  std::uint16_t port() const { return gateway_.port(); }
  BusEngine& engine() { return gateway_.engine(0); }

 private:
  static config::Config load(const std::string& yaml) {
    auto loaded = config::load_config_string(yaml, "<rtu gateway test>");
    if (!loaded) throw std::runtime_error(loaded.error().to_string());
    return std::move(*loaded);
  }
  Gateway gateway_;
};

class Client {
 public:
  Client(std::uint16_t port, int unit) {
    context_ = modbus_new_tcp("127.0.0.1", port);
    modbus_set_response_timeout(context_, 3, 0);
    if (modbus_connect(context_) != 0) throw std::runtime_error("cannot connect");
    modbus_set_slave(context_, unit);
  }
  ~Client() {
    modbus_close(context_);
    modbus_free(context_);
  }
  modbus_t* operator*() { return context_; }

 private:
  modbus_t* context_;
};

std::string config_yaml(const std::string& device) {
  return "modbus_tcp: {listen: \"127.0.0.1:0\"}\n"
         "buses:\n"
         "  - name: lift\n"
         "    device: \"" +
         device +
         "\"\n"
         "    protocol: modbus-rtu\n"
         "    baud: 128000\n"
         "    response_timeout_ms: 50\n"
         "    byte_timeout_ms: 20\n"
         "    poll_period_ms: 10\n"
         "    offline_probe_period_ms: 200\n"
         "servos:\n"
         "  - {unit: 1, bus: lift, id: 1, table: smsmb}\n"
         "  - {unit: 12, bus: lift, id: 2, table: smsmb, name: right}\n";
}

class RtuContractTest : public ::testing::Test {
 protected:
  void SetUp() override {
    simulator::BusOptions options;
    // 128000: a Modbus-table rate libmodbus 3.1.6 would run at 9600.
    options.servos = {{1, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 128'000},
                      {2, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 128'000}};
    options.seed = 1;
    bus_ = std::make_unique<simulator::SimulatedBus>(options);
    bus_->start();
    gateway_ = std::make_unique<RtuGateway>(config_yaml(bus_->slave_path()));
    // Both servos online, not just discovery done: one that missed its discovery READ (a loaded
    // machine, TSan) is offline until its next probe, and a write to it is answered 0x0B at once.
    ASSERT_TRUE(
        eventually([&] { return gateway_->engine().discovered() && gateway_->engine().cache().online_count() == 2; }));
  }

  std::unique_ptr<simulator::SimulatedBus> bus_;
  std::unique_ptr<RtuGateway> gateway_;
};

TEST_F(RtuContractTest, HoldingRegistersReadLiveAtTheServosOwnRegisterNumbers) {
  Client client(gateway_->port(), 12);
  std::uint16_t values[2] = {};
  ASSERT_EQ(modbus_read_registers(*client, 0x0A, 2, values), 2) << modbus_strerror(errno);
  EXPECT_EQ(values[0], 2);                                                // ID of unit 12's servo
  EXPECT_EQ(values[1], 1);                                                // baud code 1 = 128000
  ASSERT_TRUE(bus_->write_memory(2, 0x83, protocol::Bytes{0xFF, 0x38}));  // running speed -200
  ASSERT_EQ(modbus_read_registers(*client, 0x83, 1, values), 1) << modbus_strerror(errno);
  EXPECT_EQ(static_cast<std::int16_t>(values[0]), -200);
}

TEST_F(RtuContractTest, AddressesThatAreNoFieldReadAsZero) {
  Client client(gateway_->port(), 1);
  ASSERT_TRUE(bus_->write_memory(1, 0x15, protocol::Bytes{0x00, 0x21}));  // speed I gain 33
  std::uint16_t values[3] = {9, 9, 9};
  ASSERT_EQ(modbus_read_registers(*client, 0x15, 3, values), 3) << modbus_strerror(errno);
  EXPECT_EQ(values[0], 33);
  EXPECT_EQ(values[1], 0);
  EXPECT_EQ(values[2], 0);
}

TEST_F(RtuContractTest, WritesReachTheServoWithFc06AndFc16) {
  Client client(gateway_->port(), 1);
  ASSERT_EQ(modbus_write_register(*client, 0x84, 500), 1) << modbus_strerror(errno);  // torque limit
  EXPECT_EQ(bus_->read_field(1, "torque_limit"), 500);
  const std::uint16_t values[3] = {10, static_cast<std::uint16_t>(-100), 800};
  ASSERT_EQ(modbus_write_registers(*client, 0x82, 3, values), 3) << modbus_strerror(errno);
  EXPECT_EQ(bus_->read_field(1, "acceleration"), 10);
  EXPECT_EQ(bus_->read_field(1, "running_speed"), -100);
  EXPECT_EQ(bus_->read_field(1, "torque_limit"), 800);
}

TEST_F(RtuContractTest, CoilsAreTheBooleanFields) {
  Client client(gateway_->port(), 1);
  ASSERT_EQ(modbus_write_bit(*client, 0x81, 1), 1) << modbus_strerror(errno);  // torque switch
  EXPECT_EQ(bus_->read_field(1, "torque_switch"), 1);
  std::uint8_t bit = 0;
  ASSERT_EQ(modbus_read_bits(*client, 0x81, 1, &bit), 1) << modbus_strerror(errno);
  EXPECT_EQ(bit, 1);
}

TEST_F(RtuContractTest, RefusalsFollowTheContract) {
  Client client(gateway_->port(), 1);
  std::uint16_t value = 0;
  EXPECT_EQ(modbus_write_register(*client, 0x101, 5), -1);  // read-only present position
  EXPECT_EQ(errno, EMBXILADD);
  EXPECT_EQ(modbus_write_register(*client, 0x84, 1001), -1);  // torque limit is 0-1000
  EXPECT_EQ(errno, EMBXILVAL);
  EXPECT_EQ(modbus_read_registers(*client, 0x300, 1, &value), -1);  // beyond the table
  EXPECT_EQ(errno, EMBXILADD);
  Client nobody(gateway_->port(), 40);
  EXPECT_EQ(modbus_read_registers(*nobody, 0x0A, 1, &value), -1);
  EXPECT_EQ(errno, EMBXGPATH);
}

TEST_F(RtuContractTest, InputRegistersComeFromThePollCache) {
  Client client(gateway_->port(), 12);
  const auto position = bus_->read_field(2, "present_position");  // at rest: the power-on position
  ASSERT_TRUE(position);
  std::uint16_t values[8] = {};
  ASSERT_TRUE(eventually([&] { return modbus_read_input_registers(*client, 0x100, 8, values) == 8; }));
  EXPECT_EQ(static_cast<std::int16_t>(values[1]), *position);
  ASSERT_EQ(modbus_read_input_registers(*client, 0x101, 1, values), 1) << modbus_strerror(errno);
  EXPECT_EQ(static_cast<std::int16_t>(values[0]), *position);
  // The servo has no FC04 (docs/PROTOCOL.md §1.3): had the request reached the bus, it would be 0x01.
}

TEST_F(RtuContractTest, FactsRegistersShowTheServoOnline) {
  Client client(gateway_->port(), 12);
  std::uint16_t facts[8] = {};
  ASSERT_TRUE(eventually([&] { return modbus_read_input_registers(*client, 1000, 8, facts) == 8 && facts[1] == 1; }));
  const auto memory = bus_->read_memory(2, 0x01, 1);  // servo (model) version, shown at 1003
  ASSERT_TRUE(memory);
  EXPECT_EQ(facts[3], static_cast<std::uint16_t>((*memory)[0] << 8 | (*memory)[1]));
}

TEST_F(RtuContractTest, SilentServoIsAnswered0x0BAndComesBack) {
  Client client(gateway_->port(), 12);
  bus_->set_offline(2, true);
  std::uint16_t value = 0;
  ASSERT_TRUE(eventually([&] { return modbus_read_registers(*client, 0x0A, 1, &value) == -1 && errno == EMBXGTAR; }));
  Client other(gateway_->port(), 1);
  EXPECT_EQ(modbus_read_registers(*other, 0x0A, 1, &value), 1);
  bus_->set_offline(2, false);
  EXPECT_TRUE(eventually([&] { return modbus_read_registers(*client, 0x0A, 1, &value) == 1 && value == 2; }));
}

}  // namespace
}  // namespace sms::gateway
