// A fail-safe judged in faults (docs/PLC_GUIDE.md "Safety"): every test here combines a stop with a fault —
// a servo gone silent, the line unplugged, the gateway killed and started again, a client
// writing what the gateway refuses — and takes the simulator's own state as the witness, never
// the gateway's word. Real sms-gateway and sms-sim processes; the line is unplugged by killing
// a socat relay between them (the device path vanishes, the servos keep their state).
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/stat.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>

#include "tests/e2e/safety_support.h"
#include "tests/support/eventually.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

// The line between the gateway and the servos, as a relay that can be pulled out: socat between
// the simulator's pty and a new one behind `link`, as a USB adapter behind a udev symlink.
class Relay {
 public:
  // The simulator reads the line rate off its pty, so socat sets it there.
  Relay(std::string sim_pty, std::string link, int baud)
      : sim_pty_(std::move(sim_pty)), link_(std::move(link)), baud_(std::to_string(baud)) {
    plug();
  }

  void plug() {
    process_ = std::make_unique<ChildProcess>(
        std::vector<std::string>{"/usr/bin/socat", "PTY,link=" + link_ + ",rawer", sim_pty_ + ",rawer,b" + baud_});
    if (!eventually([&] { return std::filesystem::exists(link_); })) {
      throw std::runtime_error("socat made no " + link_ + ":\n" + process_->output());
    }
  }
  void unplug() {
    process_->signal(SIGKILL);
    process_->wait_exit(5s);
    std::error_code ignored;
    std::filesystem::remove(link_, ignored);
  }
  const std::string& device() const { return link_; }

 private:
  std::string sim_pty_;
  std::string link_;
  std::string baud_;
  std::unique_ptr<ChildProcess> process_;
};

// One bus with servo 1 of the protocol under test (and servo 2 where a test asks), a gateway on
// a configuration with a state_dir, restartable.
class SafetyCell {
 public:
  struct Options {
    std::string bus_extra;  // more keys of the bus
    std::string more_yaml;  // more servos, sync groups ...
    bool relay = false;
    bool second_servo = false;
  };

  SafetyCell(const Protocol& protocol, Options options) : protocol_(protocol), options_(std::move(options)) {
    std::vector<std::string> servos{"--servo", protocol_.sim_servo};
    if (options_.second_servo) servos.insert(servos.end(), {"--servo", "2" + protocol_.sim_servo.substr(1)});
    sim_ = std::make_unique<SimProcess>(dir_, "sim", servos);
    if (options_.relay) relay_ = std::make_unique<Relay>(sim_->pty(), dir_.file("ttyLINE"), protocol_.baud);
    ::mkdir(dir_.file("state").c_str(), 0755);
    start_gateway();
  }

  void start_gateway() {
    const std::string device = relay_ ? relay_->device() : sim_->pty();
    std::string yaml = config_for(protocol_, device, options_.bus_extra) + options_.more_yaml + "state_dir: \"" +
                       dir_.file("state") + "\"\n";
    gateway_.reset();
    gateway_ = std::make_unique<GatewayProcess>(GatewayProcess::with_config(dir_, yaml, 1));
    wait_until_polled(gateway_->port(), kUnit);
  }
  // The gateway dies (SIGKILL: no on_stop, nothing written) or stops (SIGTERM).
  void end_gateway(int signal) {
    gateway_->process().signal(signal);
    ASSERT_TRUE(gateway_->process().wait_exit(10s).has_value());
  }

  SimProcess& sim() { return *sim_; }
  Relay& relay() { return *relay_; }
  GatewayProcess& gateway() { return *gateway_; }
  std::uint16_t port() const { return gateway_->port(); }
  std::string log() { return gateway_->process().output(); }

  // Puts servo 1 in speed mode, turning.
  void spin() {
    ModbusClient plc(port(), kUnit);
    for (const Write& write : protocol_.spin) {
      const auto answer = plc.write_register(write.address, write.value);
      ASSERT_TRUE(answer.ok()) << "write " << write.address << " := " << write.value << ": " << answer.error;
    }
    ASSERT_TRUE(eventually([&] { return turning(); })) << "servo 1 never turned\n" << log();
  }
  bool turning() { return sim_->field(1, "present_speed") != 0; }

  std::uint16_t input(int address) {
    ModbusClient hmi(port(), kGateway);
    const auto answer = hmi.read_input(address, 1);
    return answer.ok() ? answer.values[0] : 0xFFFF;
  }
  int discrete(int address) {
    ModbusClient hmi(port(), kGateway);
    const auto answer = hmi.read_discrete(address, 1);
    return answer.ok() ? answer.values[0] : -1;
  }

 private:
  const Protocol& protocol_;
  Options options_;
  TempDir dir_;
  std::unique_ptr<SimProcess> sim_;
  std::unique_ptr<Relay> relay_;
  std::unique_ptr<GatewayProcess> gateway_;
};

std::string watched_bus() { return watchdog("any_write") + ", offline_probe_period_ms: 100, reopen_period_ms: 100"; }

class SafetyFaults : public testing::TestWithParam<Protocol> {};

// A servo that stops listening (deaf, as after a loose connector) while it turns, then its PLC
// goes away: the watchdog's stop cannot reach it. The stop is owed, visible, refuses motion, and
// reaches the servo the moment it listens again.
TEST_P(SafetyFaults, StopOwedToASilentServoIsDeliveredWhenItAnswersAgain) {
  SafetyCell cell(GetParam(), {watched_bus(), "", false, false});
  cell.spin();  // the PLC's last write
  ASSERT_EQ(cell.sim().control("offline 1"), "ok");
  ASSERT_TRUE(eventually([&] { return cell.input(kOwedStops) == 1; })) << cell.log();
  EXPECT_EQ(cell.input(kBus0OwedStops), 1);
  EXPECT_EQ(cell.discrete(kOwedStopInput), 1);
  EXPECT_EQ(cell.input(kBus0WatchdogState), kTripped);
  std::this_thread::sleep_for(300ms);
  // (A d55d motor stops by itself 500 ms after its last instruction: its own heartbeat.)
  if (GetParam().bus_protocol != "d55d") {
    EXPECT_TRUE(cell.turning()) << "the witness: nothing reached the deaf servo";
  }

  // Re-armed, the owed servo still refuses motion until it has taken its stop.
  ModbusClient gateway(cell.port(), kGateway);
  ASSERT_TRUE(gateway.write_coils(kWatchdogCoil, {0}).ok());
  ModbusClient plc(cell.port(), kUnit);
  EXPECT_EQ(plc.write_register(GetParam().goal.address, GetParam().goal.value).exception, 0x04) << cell.log();

  ASSERT_EQ(cell.sim().control("online 1"), "ok");
  EXPECT_TRUE(eventually([&] { return !cell.turning(); })) << cell.log();
  EXPECT_TRUE(eventually([&] { return cell.input(kOwedStops) == 0; }));
  EXPECT_EQ(cell.discrete(kOwedStopInput), 0);
  EXPECT_TRUE(cell.gateway().process().wait_for_line("took its owed safe stop", 2s)) << cell.log();
  EXPECT_TRUE(eventually([&] { return plc.write_register(GetParam().goal.address, GetParam().goal.value).ok(); }));
}

// The adapter is pulled while the servo turns, and the PLC goes away meanwhile: the stop fails,
// says so (log, failed count, owed), and is sent when the line is back, before anything else.
TEST_P(SafetyFaults, StopOwedAcrossAnUnpluggedLineIsDeliveredWhenTheLineIsBack) {
  SafetyCell cell(GetParam(), {watched_bus(), "", true, false});
  cell.spin();
  cell.relay().unplug();
  ASSERT_TRUE(cell.gateway().process().wait_for_line("bus down", 5s)) << cell.log();
  ASSERT_TRUE(cell.gateway().process().wait_for_line("safe stop (watchdog) FAILED", 5s)) << cell.log();
  EXPECT_EQ(cell.input(kOwedStops), 1);
  EXPECT_GE(cell.input(kFailedStops + 1), 1);
  EXPECT_EQ(cell.input(kBus0WatchdogState), kTripped);
  std::this_thread::sleep_for(300ms);
  if (GetParam().bus_protocol != "d55d") {
    EXPECT_TRUE(cell.turning()) << "the witness: the line was down";
  }

  cell.relay().plug();
  EXPECT_TRUE(eventually([&] { return !cell.turning(); })) << cell.log();
  EXPECT_TRUE(eventually([&] { return cell.input(kOwedStops) == 0; })) << cell.log();
}

// The gateway dies (SIGKILL) while a servo turns: started again, its on_start (hold by default
// on a bus with a watchdog) stops the servo it left turning.
TEST_P(SafetyFaults, ServoLeftTurningByAKilledGatewayIsStoppedAtStart) {
  SafetyCell cell(GetParam(), {watched_bus(), "", false, false});
  cell.spin();
  cell.end_gateway(SIGKILL);
  std::this_thread::sleep_for(200ms);
  ASSERT_TRUE(cell.turning()) << "the witness: a killed gateway stops nothing";
  cell.start_gateway();
  EXPECT_TRUE(eventually([&] { return !cell.turning(); })) << cell.log();
  EXPECT_TRUE(cell.gateway().process().wait_for_line("safe stop (on_start) sent", 2s)) << cell.log();
}

// Writes the gateway refuses — to a read-only unit, to a register that does not exist — prove
// nothing of the client that sends them: they do not keep a dead PLC's servo turning.
TEST_P(SafetyFaults, RefusedWritesDoNotFeedTheWatchdog) {
  SafetyCell cell(GetParam(),
                  {watched_bus(), "  - {unit: 2, bus: line, id: 2, table: " + GetParam().table + ", read_only: true}\n",
                   false, true});
  cell.spin();  // the PLC's last write
  std::atomic<bool> writing{true};
  std::atomic<int> refused{0};
  std::thread hmi([&] {
    ModbusClient read_only(cell.port(), 2);
    ModbusClient servo(cell.port(), kUnit);
    while (writing) {
      if (read_only.write_register(GetParam().harmless.address, GetParam().harmless.value).exception == 0x02) ++refused;
      if (servo.write_register(9999, 1).exception == 0x02) ++refused;
      std::this_thread::sleep_for(50ms);
    }
  });
  const bool stopped = eventually([&] { return !cell.turning(); });
  writing = false;
  hmi.join();
  EXPECT_TRUE(stopped) << cell.log();
  EXPECT_GT(refused.load(), 4);
  EXPECT_EQ(cell.input(kBus0WatchdogState), kTripped);
}

INSTANTIATE_TEST_SUITE_P(EveryProtocol, SafetyFaults, testing::ValuesIn(kSafetyProtocols), protocol_name);

// The latch lives on disk: a gateway killed while latched, and one stopped while its watchdog
// was tripped, come back latched and tripped, refusing motion, and stop the servo again.
TEST(SafetyRestart, EStopLatchAndTripSurviveARestart) {
  const Protocol& sts = kSafetyProtocols[0];
  SafetyCell cell(sts, {watched_bus(), "", false, false});
  cell.spin();
  ModbusClient gateway(cell.port(), kGateway);
  ASSERT_TRUE(gateway.write_coils(kEStopCoil, {1}).ok()) << cell.log();
  ASSERT_TRUE(eventually([&] { return !cell.turning(); }));
  cell.end_gateway(SIGKILL);

  // Behind the dead gateway's back the servo is set turning again (someone with a laptop).
  ASSERT_EQ(cell.sim().control("set 1 46 DC 05"), "ok");
  ASSERT_TRUE(eventually([&] { return cell.turning(); }));
  cell.start_gateway();
  EXPECT_TRUE(cell.gateway().process().wait_for_line("E-STOP was latched before the restart", 2s)) << cell.log();
  EXPECT_EQ(cell.input(kEStopLatchedRegister), 1);
  EXPECT_TRUE(eventually([&] { return !cell.turning(); })) << "a restored latch stops again\n" << cell.log();
  ModbusClient plc(cell.port(), kUnit);
  const long goal = cell.sim().field(1, "goal_position");
  EXPECT_EQ(plc.write_register(sts.goal.address, sts.goal.value).exception, 0x04);
  EXPECT_EQ(cell.sim().field(1, "goal_position"), goal);

  ModbusClient gateway_again(cell.port(), kGateway);
  ASSERT_TRUE(gateway_again.write_coils(kEStopCoil, {0}).ok());
  cell.spin();  // accepted again; the PLC is gone after it: the watchdog trips
  ASSERT_TRUE(eventually([&] { return cell.input(kBus0WatchdogState) == kTripped; })) << cell.log();
  cell.end_gateway(SIGTERM);
  cell.start_gateway();
  EXPECT_EQ(cell.input(kBus0WatchdogState), kTripped) << cell.log();
  EXPECT_EQ(cell.input(kEStopLatchedRegister), 0);
  ModbusClient plc_again(cell.port(), kUnit);
  EXPECT_EQ(plc_again.write_register(sts.goal.address, sts.goal.value).exception, 0x04);
}

// --- no jump on enable, on every path that switches torque on -------------------------------

// The no-jump cases of one table: its addresses, and how the simulator is given a stale speed.
struct NoJumpCase {
  const Protocol* protocol;
  std::string torque_field;                    // the table's field (sync group) and the simulator's
  std::vector<std::string> stale_speed;        // simulator commands: speed mode, a stale speed, torque off last
  int torque, goal, goal_speed;                // holding registers
  std::vector<std::uint16_t> torque_and_goal;  // FC16 at min(torque, goal): torque 1 and goal 2048
};
void PrintTo(const NoJumpCase& c, std::ostream* out) { *out << c.protocol->name; }

const std::vector<NoJumpCase> kNoJumpCases{
    // (A goal write switches an STS servo's torque on: the torque goes off last.)
    {&kSafetyProtocols[0], "torque_enable", {"set 1 33 01", "set 1 46 DC 05", "set 1 40 00"}, 40, 42, 46, {1, 0, 2048}},
    {&kSafetyProtocols[3],
     "torque_switch",
     {"set 1 16 00 01", "set 1 131 01 F4", "set 1 129 00 00"},
     0x81,
     0x80,
     0x83,
     {2048, 1}},
};

class NoJump : public testing::TestWithParam<NoJumpCase> {
 protected:
  NoJump()
      : cell_(*GetParam().protocol, {"",
                                     "sync_groups:\n  - {name: torque, field: " + GetParam().torque_field +
                                         ", members: [1], holding_register_start: 0}\n",
                                     false, false}) {}

  // Torque off, speed mode, a stale goal speed left in the servo's RAM.
  void stale_speed() {
    for (const auto& command : GetParam().stale_speed) ASSERT_EQ(cell_.sim().control(command), "ok") << command;
    std::this_thread::sleep_for(100ms);
    ASSERT_FALSE(cell_.turning());
  }
  void expect_still() {
    std::this_thread::sleep_for(300ms);
    EXPECT_FALSE(cell_.turning()) << cell_.log();
    EXPECT_EQ(cell_.sim().field(1, GetParam().torque_field), 1);
  }

  SafetyCell cell_;
};

TEST_P(NoJump, TorqueOnWithAGoalPositionDoesNotRunAStaleSpeed) {
  stale_speed();
  ModbusClient plc(cell_.port(), kUnit);
  const int first = std::min(GetParam().torque, GetParam().goal);
  ASSERT_TRUE(plc.write_registers(first, GetParam().torque_and_goal).ok()) << cell_.log();
  expect_still();
}

TEST_P(NoJump, SyncGroupTorqueOnDoesNotRunAStaleSpeed) {
  stale_speed();
  ModbusClient gateway(cell_.port(), kGateway);
  ASSERT_TRUE(gateway.write_registers(0, {1}).ok()) << cell_.log();
  expect_still();
}

// Torque on when it is already on switches nothing: the move under way goes on to its goal.
TEST_P(NoJump, TorqueOnWhileOnDoesNotCancelAMove) {
  ModbusClient plc(cell_.port(), kUnit);
  ASSERT_TRUE(plc.write_register(GetParam().torque, 1).ok()) << cell_.log();
  const long start = cell_.sim().field(1, "present_position");
  const std::uint16_t far = start > 2048 ? 500 : 3500;
  ASSERT_TRUE(plc.write_register(GetParam().goal_speed, 300).ok());  // slow, so the move is still under way
  ASSERT_TRUE(plc.write_register(GetParam().goal, far).ok());
  ASSERT_TRUE(eventually([&] { return cell_.turning(); })) << cell_.log();
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(plc.write_register(GetParam().torque, 1).ok()) << cell_.log();
  EXPECT_EQ(cell_.sim().field(1, "goal_position"), far);
}

INSTANTIATE_TEST_SUITE_P(TorqueTables, NoJump, testing::ValuesIn(kNoJumpCases),
                         [](const testing::TestParamInfo<NoJumpCase>& info) { return info.param.protocol->name; });

// Staged writes and ACTION exist on packet buses: sts.
class NoJumpStaged : public testing::Test {
 protected:
  NoJumpStaged() : cell_(kSafetyProtocols[0], {"", "", false, false}) {}
  SafetyCell cell_;
};

TEST_F(NoJumpStaged, StagedTorqueOnThenActionDoesNotRunAStaleSpeed) {
  for (const auto& command : kNoJumpCases[0].stale_speed) ASSERT_EQ(cell_.sim().control(command), "ok");
  std::this_thread::sleep_for(100ms);
  ASSERT_FALSE(cell_.turning());
  ModbusClient plc(cell_.port(), kUnit);
  ASSERT_TRUE(plc.write_register(512 + 40, 1).ok()) << cell_.log();
  ModbusClient gateway(cell_.port(), kGateway);
  ASSERT_TRUE(gateway.write_coils(0, {1}).ok()) << cell_.log();
  std::this_thread::sleep_for(300ms);
  EXPECT_FALSE(cell_.turning()) << cell_.log();
  EXPECT_EQ(cell_.sim().field(1, "torque_enable"), 1);
}

// A move staged before a stop does not run at the first ACTION after the reset.
TEST_F(NoJumpStaged, MoveStagedBeforeAStopDoesNotRunAtTheNextAction) {
  ModbusClient plc(cell_.port(), kUnit);
  ASSERT_TRUE(plc.write_register(40, 1).ok());
  const long start = cell_.sim().field(1, "present_position");
  const std::uint16_t far = start > 2048 ? 500 : 3500;
  ASSERT_TRUE(plc.write_register(512 + 42, far).ok());  // staged
  ModbusClient gateway(cell_.port(), kGateway);
  ASSERT_TRUE(gateway.write_coils(kEStopCoil, {1}).ok()) << cell_.log();
  ASSERT_TRUE(gateway.write_coils(kEStopCoil, {0}).ok());
  ASSERT_TRUE(gateway.write_coils(0, {1}).ok()) << cell_.log();  // ACTION
  std::this_thread::sleep_for(300ms);
  EXPECT_NE(cell_.sim().field(1, "goal_position"), far) << cell_.log();
  EXPECT_LE(std::labs(cell_.sim().field(1, "present_position") - start), 2);
}

// --- the stop's bound -------------------------------------------------------------------------

// A watchdog no longer than the bus's worst transaction could not keep its promise: the
// configuration check refuses it and says what would do.
TEST(SafetyConfig, WatchdogShorterThanTheWorstTransactionIsRefused) {
  TempDir dir;
  const std::string path = dir.file("gateway.yaml");
  std::ofstream(path) << "buses:\n  - {name: line, device: /dev/null, protocol: feetech, baud: 1000000,\n"
                         "     response_timeout_ms: 1000, watchdog: {timeout_ms: 500}}\nservos: []\n";
  ChildProcess check({bin("sms-gateway"), "--check-config", path});
  const auto status = check.wait_exit(10s);
  ASSERT_TRUE(status.has_value());
  EXPECT_EQ(*status, 2) << check.output();
  EXPECT_NE(check.output().find("is not longer than this bus's worst transaction (a fence read and the request, 3 "
                                "attempts each, each attempt response_timeout_ms 1000 + the longest frames' wire "
                                "time = 6036 ms)"),
            std::string::npos)
      << check.output();
}

}  // namespace
}  // namespace sms::e2e
