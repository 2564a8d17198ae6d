// A modbus-rtu bus from a configuration file, as an integrator runs it: sms-sim with SMSMB
// servos on a pty, sms-gateway --config with the bus, a libmodbus TCP client. Units 1 and 2 are
// SMSMB servos shown through the register map (native = their own SMSMB layout; smsmb profile
// = the same layout); unit 30 forwards PDUs to slave 3 unchanged (passthrough).
#include <gtest/gtest.h>

#include <string>

#include "tests/support/eventually.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

constexpr const char* kRtuConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: lift, device: "@DEVICE@", protocol: modbus-rtu, baud: 115200, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: lift, id: 1, table: smsmb}
  - {unit: 2, bus: lift, id: 2, table: smsmb, profile: smsmb}
  - {unit: 30, bus: lift, id: 3, table: passthrough}
)";

class RtuBusProcess : public ::testing::Test {
 protected:
  RtuBusProcess()
      : sim_(dir_, "lift",
             {"--servo", "1:smsmb:modbus-rtu:115200", "--servo", "2:smsmb:modbus-rtu:115200", "--servo",
              "3:smsmb:modbus-rtu:115200"}),
        gateway_(GatewayProcess::with_config(dir_, substitute(kRtuConfig, "@DEVICE@", sim_.pty()), 1)) {}

  TempDir dir_;
  SimProcess sim_;
  GatewayProcess gateway_;
};

TEST_F(RtuBusProcess, SmsmbServosReadAndWriteThroughTheContract) {
  wait_until_polled(gateway_.port(), 1);
  ModbusClient unit(gateway_.port(), 1);
  // Input registers come from the poll cache (the servo itself has no FC04); at rest the
  // present position is what the servo holds.
  const auto position = unit.read_input(0x101, 1);
  ASSERT_TRUE(position.ok()) << position.error;
  EXPECT_EQ(position.values[0], sim_.field(1, "present_position"));
  ASSERT_TRUE(unit.write_register(0x80, 3000).ok());  // goal position, live
  EXPECT_EQ(sim_.field(1, "goal_position"), 3000);
  EXPECT_EQ(unit.read_holding(0x80, 1).values, std::vector<std::uint16_t>{3000});
  // Exceptions by the contract's rules, answered by the gateway before the bus.
  EXPECT_EQ(unit.read_holding(0x1F0, 1).exception, 0x02);         // past the table
  EXPECT_EQ(unit.write_register(0x101, 1).exception, 0x02);       // present position is read-only
  EXPECT_EQ(unit.write_register(512 + 0x80, 1).exception, 0x02);  // no REG WRITE on Modbus servos
}

TEST_F(RtuBusProcess, SmsmbProfileShowsTheSameLayout) {
  wait_until_polled(gateway_.port(), 2);
  ModbusClient unit(gateway_.port(), 2);
  // Goal position, torque switch, acceleration, running speed: one FC16 to the servo.
  ASSERT_TRUE(unit.write_registers(0x80, {1500, 1, 10, 800}).ok());
  EXPECT_EQ(sim_.field(2, "goal_position"), 1500);
  EXPECT_EQ(sim_.field(2, "acceleration"), 10);
  EXPECT_EQ(sim_.field(2, "running_speed"), 800);
}

TEST_F(RtuBusProcess, PassthroughUnitForwardsRequestsAndTheServosOwnExceptions) {
  ModbusClient unit(gateway_.port(), 30);
  ASSERT_TRUE(unit.write_register(0x80, 2000).ok());
  EXPECT_EQ(sim_.field(3, "goal_position"), 2000);
  EXPECT_EQ(unit.read_holding(0x80, 1).values, std::vector<std::uint16_t>{2000});
  EXPECT_EQ(unit.read_input(0x101, 1).exception, 0x01);  // the servo's own answer to FC04
}

TEST_F(RtuBusProcess, OfflineServoIs0BAndComesBackByItself) {
  wait_until_polled(gateway_.port(), 1);
  ModbusClient unit(gateway_.port(), 1);
  ASSERT_EQ(sim_.control("offline 1"), "ok");
  EXPECT_TRUE(eventually([&] { return unit.read_holding(0x80, 1).exception == 0x0B; }));
  EXPECT_TRUE(ModbusClient(gateway_.port(), 2).read_holding(0x80, 1).ok());  // the other servo is served
  ASSERT_EQ(sim_.control("online 1"), "ok");
  EXPECT_TRUE(eventually([&] { return unit.read_holding(0x80, 1).ok(); }));
}

}  // namespace
}  // namespace sms::e2e
