// "No jump on enable" beyond the torque switch (docs/SAFETY.md "No jump on enable"): a d55d
// motor woken (sleep := 0) or released (brake := 0) by any path — FC06, FC05, FC15, FC16, a staged
// write and ACTION, a sync group — does not turn at the run speed it was given before, and a
// position move braked or put to sleep half-way does not resume; a write that changes the drive
// of a running servo (d55d angle limits, sts operating mode) does not start the new mode with
// stale commands. The real sms-gateway on the real sms-sim; the simulator's own state is the witness.
#include <gtest/gtest.h>

#include <cstdlib>
#include <ostream>
#include <string>
#include <vector>

#include "tests/e2e/safety_support.h"
#include "tests/support/eventually.h"

namespace sms::e2e {
namespace {

using namespace ::sms::test;  // the toolkit: tests/support

enum class Path { Fc06, Fc05, Fc15, Fc16, StagedAction, SyncGroup };
const std::vector<Path> kEveryPath{Path::Fc06, Path::Fc05, Path::Fc15, Path::Fc16, Path::StagedAction, Path::SyncGroup};
std::string name_of(Path path) {
  switch (path) {
    case Path::Fc06: return "FC06";
    case Path::Fc05: return "FC05";
    case Path::Fc15: return "FC15";
    case Path::Fc16: return "FC16";
    case Path::StagedAction: return "staged write + ACTION";
    case Path::SyncGroup: return "sync group";
  }
  return "?";
}

// d55d addresses (docs/REGISTER_MAP.md) and the gateway unit's sync group registers below.
constexpr int kCwLimit = 6;
constexpr int kCcwLimit = 8;
constexpr int kGoal = 30;
constexpr int kRunSpeed = 32;
constexpr int kActionCoil = 0;

struct Switch {
  std::string field;  // d55d field (and simulator name)
  int address;        // holding register and coil
  int sync_register;  // its sync group's register on the gateway unit
};
void PrintTo(const Switch& target, std::ostream* out) { *out << target.field; }
const Switch kSleep{"sleep", 47, 0};
const Switch kBrake{"brake", 43, 10};

class D55dCell {
 public:
  D55dCell()
      : sim_(dir_, "sim", {"--servo", "1:d55d:d55d:115200"}),
        gateway_(GatewayProcess::with_config(dir_,
                                             "buses:\n  - {name: line, device: \"" + sim_.pty() +
                                                 "\", protocol: d55d, baud: 115200, response_timeout_ms: 100}\n"
                                                 "servos:\n  - {bus: line, id: 1, table: d55d}\n"
                                                 "sync_groups:\n"
                                                 "  - {name: sleep, field: sleep, members: [1], "
                                                 "holding_register_start: 0}\n"
                                                 "  - {name: brake, field: brake, members: [1], "
                                                 "holding_register_start: 10}\n"
                                                 "logging: {level: debug}\n",
                                             1)),
        plc_(gateway_.port(), kUnit),
        gateway_unit_(gateway_.port(), kGateway) {
    wait_until_polled(gateway_.port(), kUnit);
  }

  SimProcess& sim() { return sim_; }
  std::string log() { return gateway_.process().output(); }
  long field(const std::string& name) { return sim_.field(1, name); }

  void write(int address, std::uint16_t value) {
    const auto answer = plc_.write_register(address, value);
    ASSERT_TRUE(answer.ok()) << address << " := " << value << ": " << answer.error << "\n" << log();
  }

  // `field` := value by `path`, and awaits the simulator's taking it (an ACTION and a sync group
  // are broadcasts: the gateway answers once they are on the wire).
  void set(Path path, const Switch& target, bool value) {
    SCOPED_TRACE(name_of(path) + ": " + target.field + " := " + std::to_string(value));
    Answer<std::uint16_t> answer;
    switch (path) {
      case Path::Fc06: answer = plc_.write_register(target.address, value ? 1 : 0); break;
      case Path::Fc05: answer = plc_.write_coil(target.address, value); break;
      case Path::Fc15: answer = plc_.write_coils(target.address, {static_cast<std::uint8_t>(value ? 1 : 0)}); break;
      case Path::Fc16:
        answer = plc_.write_registers(target.address, {static_cast<std::uint16_t>(value ? 1 : 0)});
        break;
      case Path::StagedAction:
        answer = plc_.write_register(512 + target.address, value ? 1 : 0);
        if (answer.ok()) answer = gateway_unit_.write_coil(kActionCoil, true);
        break;
      case Path::SyncGroup:
        answer = gateway_unit_.write_registers(target.sync_register, {static_cast<std::uint16_t>(value ? 1 : 0)});
        break;
    }
    ASSERT_TRUE(answer.ok()) << answer.error << "\n" << log();
    ASSERT_TRUE(eventually([&] { return field(target.field) == (value ? 1 : 0); }, "the simulator's " + target.field))
        << log();
  }

  // The motor stands through five more polls of the gateway (time passes on the bus, not in a sleep).
  void expect_still(const std::string& what) {
    SCOPED_TRACE(what);
    const long position = field("present_position");
    const long angle = field("accumulated_angle");
    const long requests = this->requests();
    ASSERT_TRUE(eventually([&] { return this->requests() >= requests + 5; }, "five more polls")) << log();
    EXPECT_EQ(field("present_speed"), 0) << log();
    EXPECT_EQ(field("moving"), 0);
    EXPECT_LE(std::labs(field("present_position") - position), 1);
    EXPECT_EQ(field("accumulated_angle"), angle);
  }

 private:
  long requests() {
    const std::string stats = sim_.control("stats");
    return std::stol(stats.substr(stats.find("requests=") + 9));
  }

  TempDir dir_;
  SimProcess sim_;
  GatewayProcess gateway_;
  ModbusClient plc_;
  ModbusClient gateway_unit_;
};

class NoJumpEnable : public testing::TestWithParam<Switch> {};

// Wheel mode at run speed 90: stopped by sleep or brake, then woken or released by each path.
TEST_P(NoJumpEnable, D55dInWheelModeDoesNotTurnAgainWhenWokenOrReleased) {
  const Switch& target = GetParam();
  D55dCell cell;
  cell.write(kCwLimit, 0);
  cell.write(kCcwLimit, 0);  // both limits 0: wheel mode
  for (const Path path : kEveryPath) {
    SCOPED_TRACE(name_of(path));
    cell.write(kRunSpeed, 90);
    ASSERT_TRUE(eventually([&] { return cell.field("present_speed") != 0; }, "the motor turning")) << cell.log();
    cell.set(path, target, true);
    ASSERT_TRUE(eventually([&] { return cell.field("present_speed") == 0; }, "the motor stopped")) << cell.log();
    cell.set(path, target, false);
    EXPECT_EQ(cell.field("run_speed"), 0) << "the hold (speed := 0) goes before the enabling write\n" << cell.log();
    cell.expect_still("after " + target.field + " := 0");
    EXPECT_TRUE(cell.log().find(target.field == "sleep"
                                    ? "wake: hold (speed mode: speed := 0) first"
                                    : "brake release: hold (speed mode: speed := 0) first") != std::string::npos);
  }
  // The PLC's own command after the enable still turns it.
  cell.write(kRunSpeed, 90);
  EXPECT_TRUE(eventually([&] { return cell.field("present_speed") != 0; }, "the motor turning again")) << cell.log();
}

// A position move stopped half-way by sleep or brake does not resume to its old goal when
// woken or released.
TEST_P(NoJumpEnable, D55dPositionMoveStoppedHalfWayDoesNotResume) {
  const Switch& target = GetParam();
  D55dCell cell;
  cell.write(kCwLimit, 0);
  cell.write(kCcwLimit, 360);  // position mode, 0..360°
  cell.write(kRunSpeed, 60);
  for (const Path path : kEveryPath) {
    SCOPED_TRACE(name_of(path));
    const long start = cell.field("present_position");
    const long goal = start < 180 ? start + 150 : start - 150;
    cell.write(kGoal, static_cast<std::uint16_t>(goal));
    ASSERT_TRUE(eventually([&] { return std::labs(cell.field("present_position") - start) >= 10; }, "half-way"))
        << cell.log();
    cell.set(path, target, true);
    ASSERT_TRUE(eventually([&] { return cell.field("moving") == 0; }, "the motor stopped")) << cell.log();
    const long stopped_at = cell.field("present_position");
    ASSERT_GT(std::labs(goal - stopped_at), 10) << "stopped too late to tell";
    cell.set(path, target, false);
    EXPECT_LE(std::labs(cell.field("goal_position") - stopped_at), 1)
        << "the goal is where it stopped, not " << goal << "\n"
        << cell.log();
    cell.expect_still("after " + target.field + " := 0");
  }
}

INSTANTIATE_TEST_SUITE_P(D55d, NoJumpEnable, testing::Values(kSleep, kBrake),
                         [](const testing::TestParamInfo<Switch>& info) { return info.param.field; });

// Both angle limits 0 switch a d55d motor standing in position mode to wheel mode: its run speed
// (the speed of its moves) would turn it at once.
TEST(NoJumpDriveChange, D55dAngleLimitsIntoWheelModeDoNotTurnItAtTheOldRunSpeed) {
  D55dCell cell;
  cell.write(kCwLimit, 0);
  cell.write(kCcwLimit, 360);
  cell.write(kRunSpeed, 90);
  cell.write(kGoal, static_cast<std::uint16_t>(cell.field("present_position")));
  ASSERT_TRUE(eventually([&] { return cell.field("moving") == 0; }, "at rest")) << cell.log();
  cell.write(kCcwLimit, 0);  // wheel mode
  EXPECT_EQ(cell.field("run_speed"), 0) << cell.log();
  cell.expect_still("in wheel mode");
  EXPECT_NE(cell.log().find("drive change (position mode -> speed mode)"), std::string::npos) << cell.log();
  cell.write(kRunSpeed, 90);
  EXPECT_TRUE(eventually([&] { return cell.field("present_speed") != 0; }, "the motor turning")) << cell.log();
}

// An sts servo holding its position with a goal speed set (the speed of its moves) is switched to
// constant-speed mode: it does not run at that speed until the PLC writes one.
TEST(NoJumpDriveChange, StsOperatingModeIntoSpeedModeDoesNotRunTheOldGoalSpeed) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--servo", "1:sts"});
  auto gateway = GatewayProcess::with_config(dir,
                                             "buses:\n  - {name: line, device: \"" + sim.pty() +
                                                 "\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}\n"
                                                 "servos:\n  - {bus: line, id: 1, table: sts}\n"
                                                 "sync_groups:\n  - {name: modes, field: operating_mode, "
                                                 "members: [1], holding_register_start: 0}\n"
                                                 "logging: {level: debug}\n",
                                             1);
  wait_until_polled(gateway.port(), kUnit);
  ModbusClient plc(gateway.port(), kUnit);
  ModbusClient gateway_unit(gateway.port(), kGateway);
  for (const bool sync_group : {false, true}) {
    SCOPED_TRACE(sync_group ? "sync group" : "FC06");
    ASSERT_TRUE(plc.write_register(33, 0).ok());  // position mode
    ASSERT_TRUE(plc.write_register(46, 1500).ok());
    ASSERT_TRUE(plc.write_register(42, static_cast<std::uint16_t>(sim.field(1, "present_position"))).ok());
    ASSERT_TRUE(eventually([&] { return sim.field(1, "moving") == 0; }, "at rest"));
    ASSERT_EQ(sim.field(1, "torque_enable"), 1);
    const auto answer = sync_group ? gateway_unit.write_registers(0, {1}) : plc.write_register(33, 1);
    ASSERT_TRUE(answer.ok()) << answer.error << "\n" << gateway.process().output();
    ASSERT_TRUE(eventually([&] { return sim.field(1, "operating_mode") == 1; }, "speed mode"));
    EXPECT_EQ(sim.field(1, "goal_speed"), 0) << gateway.process().output();
    const long position = sim.field(1, "present_position");
    const std::string stats = sim.control("stats");
    const long requests = std::stol(stats.substr(stats.find("requests=") + 9));
    ASSERT_TRUE(eventually([&] {
      const std::string now = sim.control("stats");
      return std::stol(now.substr(now.find("requests=") + 9)) >= requests + 5;
    }));
    EXPECT_EQ(sim.field(1, "present_speed"), 0) << gateway.process().output();
    EXPECT_LE(std::labs(sim.field(1, "present_position") - position), 1);
  }
  EXPECT_NE(gateway.process().output().find("drive change (position mode -> speed mode): goal := present position"),
            std::string::npos);
  ASSERT_TRUE(plc.write_register(46, 800).ok());
  EXPECT_TRUE(eventually([&] { return sim.field(1, "present_speed") != 0; }, "the servo turning"));
}

}  // namespace
}  // namespace sms::e2e
