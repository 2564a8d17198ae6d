// Motion safety end to end (docs/PLC_GUIDE.md "Safety"): the real sms-gateway on a configuration
// file, the real sms-sim on a pty, libmodbus clients. For every protocol and a table of each
// (feetech sts and sms1, d55d, modbus-rtu smsmb): a servo set turning at constant speed by a
// client is stopped by the watchdog when the client vanishes or stops counting its heartbeat,
// HMI reads do not keep it alive, the e-stop refuses motion writes with 0x04 until reset and
// the reset moves nothing, SIGTERM performs on_stop, and torque on does not jump.
#include <gtest/gtest.h>

#include <signal.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <thread>

#include "tests/e2e/safety_support.h"
#include "tests/support/eventually.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

class Safety : public testing::TestWithParam<Protocol> {
 protected:
  void start(const std::string& bus_extra) {
    sim_ = std::make_unique<SimProcess>(dir_, "sim", std::vector<std::string>{"--servo", GetParam().sim_servo});
    gateway_ = std::make_unique<GatewayProcess>(
        GatewayProcess::with_config(dir_, config_for(GetParam(), sim_->pty(), bus_extra), 1));
    wait_until_polled(gateway_->port(), kUnit);
  }

  // Puts the servo in speed mode and waits until it turns.
  void spin(ModbusClient& plc) {
    for (const Write& write : GetParam().spin) {
      const auto answer = plc.write_register(write.address, write.value);
      ASSERT_TRUE(answer.ok()) << "write " << write.address << " := " << write.value << ": " << answer.error;
    }
    ASSERT_TRUE(eventually([&] { return sim_->field(1, "present_speed") != 0; })) << "servo 1 never turned\n"
                                                                                  << gateway_->process().output();
  }

  bool stopped() { return sim_->field(1, "present_speed") == 0; }

  std::uint16_t gateway_register(int address) {
    ModbusClient hmi(gateway_->port(), kGateway);
    const auto answer = hmi.read_input(address, 1);
    EXPECT_TRUE(answer.ok()) << answer.error;
    return answer.ok() ? answer.values[0] : 0xFFFF;
  }

  TempDir dir_;
  std::unique_ptr<SimProcess> sim_;
  std::unique_ptr<GatewayProcess> gateway_;
};

TEST_P(Safety, WatchdogStopsTheServoWhenItsClientVanishesWhileHmiReadsGoOn) {
  start(watchdog("any_write"));
  {
    ModbusClient plc(gateway_->port(), kUnit);
    spin(plc);
  }  // the PLC is gone: disconnected mid-move

  // An HMI keeps reading (live and cached): reads never feed the watchdog.
  std::atomic<bool> reading{true};
  std::atomic<int> reads{0};
  std::thread hmi([&] {
    ModbusClient client(gateway_->port(), kUnit);
    while (reading) {
      if (client.read_input(GetParam().present_address, 1).ok() &&
          client.read_holding(GetParam().goal_address, 1).ok()) {
        ++reads;
      }
      std::this_thread::sleep_for(10ms);
    }
  });
  const bool stopped_in_time = eventually([&] { return stopped(); });
  reading = false;
  hmi.join();
  ASSERT_TRUE(stopped_in_time) << gateway_->process().output();
  EXPECT_GT(reads.load(), 0);
  EXPECT_EQ(gateway_register(kBus0WatchdogState), kTripped);
  EXPECT_EQ(gateway_register(kBus0Trips + 1), 1);
  // The cause is recorded once the stop's last frame is acknowledged, a moment after the servo
  // (the witness above) has taken it.
  EXPECT_TRUE(eventually([&] { return gateway_register(kBus0LastCause) == 1; }))  // watchdog
      << "cause " << gateway_register(kBus0LastCause);
  EXPECT_TRUE(gateway_->process().wait_for_line("WATCHDOG TRIPPED", 2s));

  // Tripped: motion writes refused with 0x04 until a client re-arms it; re-arming moves nothing.
  ModbusClient plc(gateway_->port(), kUnit);
  const auto refused = plc.write_register(GetParam().goal.address, GetParam().goal.value);
  EXPECT_EQ(refused.exception, 0x04) << refused.error;
  ModbusClient gateway(gateway_->port(), kGateway);
  const auto tripped_coil = gateway.read_coils(kWatchdogCoil, 1);
  ASSERT_TRUE(tripped_coil.ok());
  EXPECT_EQ(tripped_coil.values[0], 1);
  ASSERT_TRUE(gateway.write_coils(kWatchdogCoil, {0}).ok());
  std::this_thread::sleep_for(100ms);
  EXPECT_TRUE(stopped());
  EXPECT_EQ(gateway_register(kBus0WatchdogState), 1);  // armed
  const auto accepted = plc.write_register(GetParam().harmless.address, GetParam().harmless.value);
  EXPECT_TRUE(accepted.ok()) << accepted.error;
}

TEST_P(Safety, FrozenPlcThatKeepsItsConnectionTripsTheHeartbeatWatchdog) {
  // A 2 s watchdog: a count every 50 ms must keep it fed on a loaded machine too, where one
  // write may wait hundreds of milliseconds for a core.
  constexpr int kTimeoutMs = 2000;
  start(watchdog("heartbeat_register", kTimeoutMs));
  ModbusClient plc(gateway_->port(), kUnit);
  spin(plc);
  ModbusClient heartbeat(gateway_->port(), kGateway);
  // A live PLC counts: two timeouts' worth of changing values keep the servo turning.
  std::uint16_t count = 0;
  const auto live_until = std::chrono::steady_clock::now() + 2 * std::chrono::milliseconds(kTimeoutMs);
  while (std::chrono::steady_clock::now() < live_until) {
    ASSERT_TRUE(heartbeat.write_register(kHeartbeatRegister, ++count).ok());
    std::this_thread::sleep_for(50ms);
  }
  EXPECT_EQ(gateway_register(kBus0WatchdogState), kRunning) << gateway_->process().output();
  EXPECT_FALSE(stopped());
  // Frozen: the connection stays, the same value keeps arriving, the goal is read back.
  const bool stopped_in_time = eventually([&] {
    heartbeat.write_register(kHeartbeatRegister, count);
    plc.read_holding(GetParam().goal_address, 1);
    return stopped();
  });
  ASSERT_TRUE(stopped_in_time) << gateway_->process().output();
  EXPECT_EQ(gateway_register(kBus0WatchdogState), kTripped);
  const auto read_back = heartbeat.read_holding(kHeartbeatRegister, 1);
  ASSERT_TRUE(read_back.ok());
  EXPECT_EQ(read_back.values[0], count);
}

TEST_P(Safety, EStopRefusesMotionUntilResetAndTheResetMovesNothing) {
  start("");
  ModbusClient plc(gateway_->port(), kUnit);
  spin(plc);
  ModbusClient gateway(gateway_->port(), kGateway);
  ASSERT_TRUE(gateway.write_coils(kEStopCoil, {1}).ok()) << gateway_->process().output();
  ASSERT_TRUE(eventually([&] { return stopped(); }));
  EXPECT_TRUE(gateway_->process().wait_for_line("E-STOP latched", 2s));

  // Latched: every motion write refused, reads and harmless writes served.
  const auto goal = plc.write_register(GetParam().goal.address, GetParam().goal.value);
  EXPECT_EQ(goal.exception, 0x04) << goal.error;
  for (const Write& write : GetParam().spin) {
    const auto answer = plc.write_register(write.address, write.value);
    if (write.value != 0) {
      EXPECT_EQ(answer.exception, 0x04) << "write " << write.address;
    }
  }
  EXPECT_TRUE(plc.read_holding(GetParam().goal_address, 1).ok());
  EXPECT_TRUE(plc.read_input(GetParam().present_address, 1).ok());
  EXPECT_TRUE(plc.write_register(GetParam().harmless.address, GetParam().harmless.value).ok());
  if (GetParam().torque_off) {
    EXPECT_TRUE(plc.write_register(GetParam().torque_off->address, GetParam().torque_off->value).ok());
  }
  const auto latched = gateway.read_coils(kEStopCoil, 1);
  ASSERT_TRUE(latched.ok());
  EXPECT_EQ(latched.values[0], 1);
  const auto latched_input = gateway.read_discrete(0, 1);
  ASSERT_TRUE(latched_input.ok());
  EXPECT_EQ(latched_input.values[0], 1);
  EXPECT_EQ(gateway_register(kBus0LastCause), 2);  // e-stop

  // Reset: nothing moves; motion writes work again.
  const long goal_before = sim_->field(1, "goal_position");
  ASSERT_TRUE(gateway.write_coils(kEStopCoil, {0}).ok());
  std::this_thread::sleep_for(200ms);
  EXPECT_TRUE(stopped());
  EXPECT_EQ(sim_->field(1, "goal_position"), goal_before);
  const auto after = plc.write_register(GetParam().goal.address, GetParam().goal.value);
  EXPECT_TRUE(after.ok()) << after.error;
}

TEST_P(Safety, SigtermPerformsOnStopBeforeTheGatewayExits) {
  start(", on_stop: hold");
  {
    ModbusClient plc(gateway_->port(), kUnit);
    spin(plc);
  }
  gateway_->process().signal(SIGTERM);
  const auto status = gateway_->process().wait_exit(10s);
  ASSERT_TRUE(status.has_value());
  EXPECT_EQ(*status, 0) << gateway_->process().output();
  EXPECT_TRUE(eventually([&] { return stopped(); })) << gateway_->process().output();
  EXPECT_NE(gateway_->process().output().find("safe stop (the gateway is stopping)"), std::string::npos)
      << gateway_->process().output();
}

INSTANTIATE_TEST_SUITE_P(EveryProtocol, Safety, testing::ValuesIn(kSafetyProtocols), protocol_name);

// "No jump on enable": a servo whose torque is off and whose goal is far from where it stands
// holds where it is when a client switches its torque on.
TEST(SafetyTorqueOn, TorqueOnHoldsThePresentPositionInsteadOfAStaleGoal) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--servo", "1:sts"});
  auto gateway =
      GatewayProcess::with_config(dir,
                                  "buses:\n  - {name: line, device: \"" + sim.pty() +
                                      "\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}\n"
                                      "servos:\n  - {bus: line, id: 1, table: sts}\nlogging: {level: debug}\n",
                                  1);
  wait_until_polled(gateway.port(), kUnit);
  ModbusClient plc(gateway.port(), kUnit);
  // A stale goal far away, left in the servo's RAM behind the gateway's back, with the torque off.
  // A goal write switches an STS servo's torque on (and the simulated one starts moving), so the
  // torque goes off right after it, wherever the motor then stands.
  const long start = sim.field(1, "present_position");
  const long stale = start > 2048 ? start - 1500 : start + 1500;
  char set_goal[40];
  std::snprintf(set_goal, sizeof set_goal, "set 1 42 %02lX %02lX", stale & 0xFF, (stale >> 8) & 0xFF);
  ASSERT_EQ(sim.control(set_goal), "ok");
  ASSERT_EQ(sim.control("set 1 40 00"), "ok");  // torque off: the motor stops where it is
  ASSERT_EQ(sim.field(1, "goal_position"), stale);
  const long present = sim.field(1, "present_position");
  ASSERT_TRUE(plc.write_register(40, 1).ok()) << gateway.process().output();  // torque on
  EXPECT_EQ(sim.field(1, "torque_enable"), 1);
  // The gateway held the goal itself (the simulated firmware would too; a real one may not).
  EXPECT_TRUE(gateway.process().wait_for_line("torque on: hold (position mode: goal := present position", 2s))
      << gateway.process().output();
  const long goal = sim.field(1, "goal_position");
  EXPECT_LE(std::labs(goal - present), 2) << "goal " << goal << ", stood at " << present;
  std::this_thread::sleep_for(300ms);
  EXPECT_LE(std::labs(sim.field(1, "present_position") - present), 2);
}

// The e-stop holds on every way in: sync groups, staged writes and ACTION, passthrough units.
TEST(SafetyEStop, CoversSyncGroupsStagedWritesActionAndPassthroughUnits) {
  TempDir dir;
  SimProcess arm(dir, "arm", {"--servo", "1:sts", "--servo", "2:sts"});
  SimProcess line(dir, "line", {"--servo", "7:smsmb:modbus-rtu:115200"});
  auto gateway = GatewayProcess::with_config(
      dir,
      "buses:\n"
      "  - {name: arm, device: \"" +
          arm.pty() +
          "\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}\n"
          "  - {name: line, device: \"" +
          line.pty() +
          "\", protocol: modbus-rtu, baud: 115200, response_timeout_ms: 200}\n"
          "servos:\n"
          "  - {bus: arm, id: 1, table: sts}\n"
          "  - {bus: arm, id: 2, table: sts}\n"
          "  - {bus: line, id: 7, table: passthrough}\n"
          "sync_groups:\n"
          "  - {name: goals, field: goal_position, members: [1, 2], holding_register_start: 0}\n"
          "  - {name: accelerations, field: acceleration, members: [1, 2], holding_register_start: 10}\n",
      2);
  wait_until_polled(gateway.port(), 1);
  ModbusClient gateway_unit(gateway.port(), kGateway);
  ModbusClient servo(gateway.port(), 1);
  ModbusClient passthrough(gateway.port(), 7);
  ASSERT_TRUE(servo.write_register(512 + 42, 1000).ok());  // staged before the e-stop
  ASSERT_TRUE(gateway_unit.write_coils(kEStopCoil, {1}).ok()) << gateway.process().output();

  EXPECT_EQ(gateway_unit.write_registers(0, {1000, 1000}).exception, 0x04);  // sync group of goals
  EXPECT_TRUE(gateway_unit.write_registers(10, {5, 5}).ok());                // of accelerations: no motion
  EXPECT_EQ(servo.write_register(512 + 42, 1500).exception, 0x04);           // staged goal
  EXPECT_EQ(gateway_unit.write_coils(0, {1}).exception, 0x04);               // ACTION
  EXPECT_EQ(passthrough.write_register(0x80, 1000).exception, 0x04);         // a foreign slave's write
  EXPECT_TRUE(passthrough.read_holding(0x101, 1).ok());                      // its reads go on
  EXPECT_EQ(arm.field(1, "goal_position"), arm.field(1, "present_position"));

  ASSERT_TRUE(gateway_unit.write_coils(kEStopCoil, {0}).ok());
  EXPECT_TRUE(gateway_unit.write_registers(0, {2100, 2100}).ok());
  EXPECT_TRUE(passthrough.write_register(0x82, 10).ok());
  EXPECT_TRUE(eventually([&] { return arm.field(2, "goal_position") == 2100; }));
}

// 40 servos stopping the same way: their state is read in one SYNC READ frame, and they need
// two SYNC WRITE frames of the 6-byte goal block (LEN carries 35): every one of them stops, in a
// handful of frames instead of 40 READs, and the gateway lives on.
TEST(SafetyEStop, StopsMoreServosThanOneSyncWriteFrameCarries) {
  constexpr int kServos = 40;
  TempDir dir;
  SimProcess sim(dir, "sim", {"--ids", "1-40"});
  // One poll cycle at start, then none for a minute: the frames counted are the stop's.
  std::string yaml =
      "buses:\n  - {name: arm, device: \"" + sim.pty() +
      "\", protocol: feetech, baud: 1000000, poll_period_ms: 60000, response_timeout_ms: 200}\nservos:\n";
  for (int id = 1; id <= kServos; ++id) yaml += "  - {bus: arm, id: " + std::to_string(id) + ", table: sts}\n";
  auto gateway = GatewayProcess::with_config(dir, yaml, 1);
  wait_until_polled(gateway.port(), kServos);
  ModbusClient plc(gateway.port(), 1);
  for (int id = 1; id <= kServos; ++id) {
    plc.set_unit(id);
    ASSERT_TRUE(plc.write_register(33, 1).ok());
    ASSERT_TRUE(plc.write_register(46, 800).ok());
  }
  ASSERT_TRUE(eventually([&] { return sim.field(kServos, "present_speed") != 0; }));
  ModbusClient gateway_unit(gateway.port(), kGateway);
  const auto requests = [&] {
    const std::string stats = sim.control("stats");
    return std::stol(stats.substr(stats.find("requests=") + 9));
  };
  const long before = requests();
  ASSERT_TRUE(gateway_unit.write_coils(kEStopCoil, {1}).ok()) << gateway.process().output();
  for (int id = 1; id <= kServos; ++id) {
    EXPECT_TRUE(eventually([&] { return sim.field(id, "present_speed") == 0; })) << "servo " << id;
  }
  // One SYNC READ of the 40 states, two SYNC WRITE frames.
  EXPECT_EQ(requests() - before, 3) << gateway.process().output();
  EXPECT_TRUE(gateway_unit.read_input(0, 1).ok());
}

}  // namespace
}  // namespace sms::e2e
