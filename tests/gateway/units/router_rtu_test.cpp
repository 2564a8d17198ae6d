// Units on a modbus-rtu bus through the whole gateway, in-process: SMSMB servos shown with
// their own register map (table smsmb), and a passthrough unit whose PDUs are forwarded to the
// slave unchanged, exceptions included.
#include <gtest/gtest.h>

#include <optional>

#include "tests/support/engine_conformance.h"
#include "tests/support/processes.h"
#include "tests/support/simulated_gateway.h"

namespace sms::gateway::testing {
namespace {

simulator::BusOptions smsmb_bus() {
  return untimed_bus({{1, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 115200},
                      {2, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 115200}});
}

const char* const kRtuConfig = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: lift, device: "@DEVICE@", protocol: modbus-rtu, baud: 115200, poll_period_ms: 10,
     response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: lift, id: 1, table: smsmb}
  - {unit: 30, bus: lift, id: 2, table: passthrough}
)";

// The same modbus-rtu bus beside a packet bus "arm" (one sts servo, unit 40) on a simulator of its own.
const char* const kRtuAndPacketConfig = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: lift, device: "@DEVICE@", protocol: modbus-rtu, baud: 115200, poll_period_ms: 10,
     response_timeout_ms: 100, retries: 1}
  - {name: arm, device: "@ARM@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: lift, id: 1, table: smsmb}
  - {unit: 40, bus: arm, id: 1, table: sts}
)";

class RouterRtu : public ::testing::Test {
 protected:
  void SetUp() override { gateway_ = std::make_unique<SimulatedGateway>(smsmb_bus(), kRtuConfig); }
  // The gateway again, on kRtuAndPacketConfig.
  void add_packet_bus() {
    gateway_.reset();
    arm_.emplace(sts_bus(1));
    arm_->start();
    gateway_ = std::make_unique<SimulatedGateway>(smsmb_bus(),
                                                  test::substitute(kRtuAndPacketConfig, "@ARM@", arm_->slave_path()));
  }
  simulator::SimulatedBus& sim() { return gateway_->bus(); }
  std::uint16_t port() const { return gateway_->port(); }
  std::optional<simulator::SimulatedBus> arm_;  // outlives the gateway that has its line open
  std::unique_ptr<SimulatedGateway> gateway_;
};

TEST_F(RouterRtu, SmsmbServoRegistersReadAndWriteThroughTheRegisterMap) {
  gateway_->wait_until_polled(1);
  ModbusClient client(port(), 1);
  const auto feedback = client.read_input(0x101, 1);  // from the poll cache (the servo has no FC04)
  ASSERT_TRUE(feedback.ok()) << feedback.error;
  EXPECT_EQ(feedback.values[0], static_cast<std::uint16_t>(*sim().read_field(1, "present_position")));  // at rest
  ASSERT_TRUE(client.write_register(0x80, 3000).ok());                                                  // goal position
  EXPECT_EQ(*sim().read_field(1, "goal_position"), 3000);
  EXPECT_EQ(client.read_holding(0x80, 1).values, std::vector<std::uint16_t>{3000});
  EXPECT_EQ(client.write_register(512 + 0x80, 1).exception, 0x02);  // no REG WRITE on Modbus servos
}

TEST_F(RouterRtu, PassthroughUnitForwardsPdusAndExceptionsUnchanged) {
  ModbusClient client(port(), 30);
  ASSERT_TRUE(client.write_register(0x80, 2000).ok());  // slave 2's goal position
  EXPECT_EQ(*sim().read_field(2, "goal_position"), 2000);
  EXPECT_EQ(client.read_holding(0x80, 1).values, std::vector<std::uint16_t>{2000});
  // The servo itself answers FC04 with exception 0x01 (docs/PROTOCOL.md §1.3); the gateway passes it on.
  EXPECT_EQ(client.read_input(0x101, 1).exception, 0x01);
  // Feetech's "query slave ID" (0x11) is no function of the gateway's, but the slave has it.
  const auto identity = client.raw({0x11}, 30);
  ASSERT_EQ(identity.exception, 0) << identity.error;
  ASSERT_GE(identity.values.size(), 3u);
  EXPECT_EQ(identity.values[0], 0x11);
}

// Gateway coil 0 broadcasts ACTION on every packet bus (docs/PLC_GUIDE.md "The gateway unit"): the
// packet bus runs its staged write; the modbus-rtu bus, which has no staged writes, gets no frame
// for it (its simulator hears only the engine's poll reads).
TEST_F(RouterRtu, ActionCoilSkipsModbusBuses) {
  add_packet_bus();
  gateway_->wait_until_polled(40);
  ModbusClient servo(port(), 40);
  const auto goal_before = *arm_->read_field(1, "goal_position");
  ASSERT_NE(goal_before, 1500);
  ASSERT_TRUE(servo.write_register(512 + 42, 1500).ok());  // staged (REG WRITE) goal position
  ASSERT_EQ(*arm_->read_field(1, "goal_position"), goal_before);

  conformance::FrameLog lift(sim());
  ModbusClient gateway(port(), 255);
  ASSERT_TRUE(gateway.write_coil(0, true).ok());
  EXPECT_TRUE(eventually([&] { return *arm_->read_field(1, "goal_position") == 1500; },
                         "bus arm's ACTION running the staged goal position"));
  // The lift's engine has gone round since (its poll reached the simulator): had the coil given it
  // anything to send, it would have been sent by now.
  const std::size_t seen = lift.frames().size();
  EXPECT_TRUE(eventually([&] { return lift.frames().size() > seen + 1; }, "two more poll reads on bus lift"));
  for (const auto& frame : lift.frames()) {
    EXPECT_NE(frame.id, 0) << "a broadcast reached the modbus-rtu bus (function " << int(frame.code) << ")";
    EXPECT_EQ(frame.code, 0x03) << "slave " << int(frame.id) << " got function " << int(frame.code)
                                << ", not a poll read";
  }
}

}  // namespace
}  // namespace sms::gateway::testing
