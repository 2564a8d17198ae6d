// A stop stops where the axis is (docs/SAFETY.md "Stop distance"): every safe stop writes the
// stop's own ramp with the hold, in the same frame, so an axis that a move left on a gentle ramp
// does not coast on past the goal the stop gave it and drive back. The real sms-gateway on the
// real sms-sim; the witness is the simulator's own record of the stop's goal write: where the
// motor was when it arrived, where it stood, whether it turned back, and when it stood still.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <iostream>
#include <string>
#include <vector>

#include "tests/e2e/safety_support.h"
#include "tests/e2e/sim_motion.h"
#include "tests/support/eventually.h"

namespace sms::e2e {
namespace {

using namespace std::chrono_literals;

// One table's axis set on a gentle ramp and sent far: the stop comes mid-move, at speed.
struct StopCase {
  std::string name;
  std::string sim_servo;  // sms-sim --servo, without the id
  std::string bus_protocol;
  int baud;
  std::string table;
  std::vector<Write> setup;  // torque on, speed, the gentle ramp
  int goal_address;
  int start;     // the simulator's power-on position
  int distance;  // how far the move goes
  // Position units the axis may stand from where it was when the stop's frame arrived: 20 steps,
  // d55d (1 deg a unit) 2.
  int tolerance;
  int move_time_ms;  // a timed move over `distance`: its ramp is the plan's
};

void PrintTo(const StopCase& c, std::ostream* out) { *out << c.name; }

// Acceleration 5 (500 steps/s^2) on the Feetech tables: left as it is, a stop at speed coasts on
// hundreds of steps. d55d: run speed 50 deg/s, acceleration 9 (90 deg/s^2).
const std::vector<StopCase> kCases{
    {"sts", "sts", "feetech", 1000000, "sts", {{40, 1}, {41, 5}, {46, 2400}}, 42, 2048, 1500, 20, 3000},
    {"sms1", "sms1", "feetech", 1000000, "sms1", {{40, 1}, {41, 5}, {46, 1500}}, 42, 2048, 1500, 20, 3000},
    // scs has no ramp: it changes speed at once, and its hold is goal := present position.
    {"scs", "scs", "feetech", 1000000, "scs", {{40, 1}, {46, 150}}, 42, 512, 400, 20, 3000},
    // d55d brakes at 2540 deg/s^2 at best: from 50 deg/s it runs on 0.5 deg, plus the ~5 ms the
    // stop frame takes at 115 200 bit/s; 2 deg is the 20 steps of the others (1.8 deg).
    {"d55d", "d55d:d55d:115200", "d55d", 115200, "d55d", {{8, 3600}, {32, 50}, {34, 9}, {35, 9}}, 30, 0, 150, 2, 8000},
    {"smsmb",
     "smsmb:modbus-rtu:115200",
     "modbus-rtu",
     115200,
     "smsmb",
     {{0x81, 1}, {0x82, 5}, {0x83, 2400}},
     0x80,
     2048,
     1500,
     20,
     3000},
};

std::string case_name(const testing::TestParamInfo<StopCase>& info) { return info.param.name; }

class StopRamp : public testing::TestWithParam<StopCase> {
 protected:
  // A cell of one servo at unit 1; `bus_extra` adds keys to the bus.
  void start(const std::string& bus_extra = "", const std::string& more_yaml = "") {
    const StopCase& c = GetParam();
    sim_ = std::make_unique<SimProcess>(dir_, "line", std::vector<std::string>{"--servo", "1:" + c.sim_servo});
    const std::string yaml =
        "buses:\n  - {name: line, device: \"" + sim_->pty() + "\", protocol: " + c.bus_protocol +
        ", baud: " + std::to_string(c.baud) +
        // 200 ms: a loaded machine holds the simulator longer than 100 (the test is about the
        // stop, not the timeout), and the watchdog test's 1000 ms must outlast 2 x 2 attempts;
        // d55d 100 ms: its motors stop themselves after 500 ms without an instruction.
        ", poll_period_ms: 20, response_timeout_ms: " + (c.bus_protocol == "d55d" ? "100" : "200") + ", retries: 1" +
        bus_extra + "}\nservos:\n  - {unit: 1, bus: line, id: 1, table: " + c.table + "}\n" + more_yaml;
    yaml_ = yaml;
    start_gateway();
  }

  void start_gateway() {
    gateway_ = std::make_unique<GatewayProcess>(GatewayProcess::with_config(dir_, yaml_, 1));
    wait_until_polled(gateway_->port(), kUnit);
    plc_ = std::make_unique<ModbusClient>(gateway_->port(), kUnit);
    panel_ = std::make_unique<ModbusClient>(gateway_->port(), kGateway);
  }

  // Sets the axis going on its gentle ramp (or in a timed move, the plan's) and waits until it is
  // 1/`part` of the way, at speed.
  void move_far(bool timed = false, int part = 3) {
    const StopCase& c = GetParam();
    for (const Write& write : c.setup) {
      ASSERT_TRUE(plc_->write_register(write.address, write.value).ok()) << "setup write " << write.address << log();
    }
    const auto goal = static_cast<std::uint16_t>(c.start + c.distance);
    if (timed) {  // the group's goal and move time in one FC16 (holding 0 and 1 of unit 255)
      ASSERT_TRUE(panel_->write_registers(0, {goal, static_cast<std::uint16_t>(c.move_time_ms)}).ok()) << log();
    } else {
      ASSERT_TRUE(plc_->write_register(c.goal_address, goal).ok()) << log();
    }
    ASSERT_TRUE(eventually([&] { return motion_of(*sim_, 1).position >= c.start + c.distance / part; }, 10s))
        << "the axis never got 1/" << part << " of the way\n"
        << sim_->control("motion 1") << log();
    moving_ = motion_of(*sim_, 1);
    ASSERT_EQ(moving_.goal, c.start + c.distance) << "still on its way to the far goal";
  }

  // The stop that came after move_far(): the simulator's record of its goal write, once the axis
  // stands at that goal.
  Motion stopped() {
    Motion stop;
    const bool stood = eventually(
        [&] {
          stop = motion_of(*sim_, 1);
          return stop.started_us > moving_.started_us && stop.arrived_us >= 0 && stop.position == stop.goal;
        },
        10s);
    if (!stood && hold_unreadable_by_the_machine()) {
      unreadable_ = true;
      return stop;
    }
    EXPECT_TRUE(stood) << "the axis did not come to stand at the stop's goal: " << sim_->control("motion 1") << log();
    return stop;
  }

  // The product's rule where a loaded machine held the simulator past every attempt of the hold's
  // read: the servo's state is unknown, so its stop is a torque off (docs/SAFETY.md), which the
  // claims here are not about. True (and said) only where the simulator witnessed a hold of at
  // least one attempt's time.
  bool hold_unreadable_by_the_machine() {
    if (gateway_->process().output().find("cannot hold it (") == std::string::npos) return false;
    const auto attempt = std::chrono::milliseconds(GetParam().bus_protocol == "d55d" ? 100 : 200);
    if (!sim_held(*sim_, attempt, started_)) return false;
    std::cout << "the machine held the simulator past the hold's read (" << sim_->control("holds")
              << "): the stop was a torque off, the product's rule; its position is not checked\n";
    return true;
  }

  // Every stop: within the tolerance of where the axis was when the stop's frame arrived, turning
  // back at most a quarter of it (5 steps, d55d none), standing within 300 ms. The goal goes ahead
  // by what the axis covers while the frame is on its way, estimated from the read's answer; a
  // frame a loaded host held back longer arrives later, and the servo pulls back what the axis
  // covered meanwhile: at most its run-on since that read (sim_motion.h), never a ramp's run-on.
  void expect_stopped_where_it_was(const Motion& stop, const std::string& what) {
    if (unreadable_) return;
    const StopCase& c = GetParam();
    const long late = run_on_since_read(stop);
    EXPECT_LE(stop.position - stop.at_goal_write, c.tolerance)
        << what << ": the axis was at " << stop.at_goal_write << " when the stop's goal arrived and stood at "
        << stop.position << log();
    EXPECT_LE(stop.at_goal_write - stop.position, c.tolerance + late)
        << what << ": the axis was at " << stop.at_goal_write << " when the stop's goal arrived (at "
        << stop.read_before_goal << " when it answered the read before) and stood at " << stop.position << log();
    EXPECT_LE(stop.turned_back, c.tolerance / 4 + late)
        << what << ": the axis drove back to the stop's goal (it ran on " << late
        << " between the read and the stop's arrival)" << log();
    EXPECT_LE(stop.arrived_us - stop.started_us, 300'000)
        << what << ": stood " << stop.arrived_us - stop.started_us << " us after the stop's goal" << log();
    EXPECT_LT(stop.position, c.start + c.distance - 50) << what << ": the stop came too late to show anything";
  }

  std::string log() { return "\n" + gateway_->process().output(); }

  TempDir dir_;
  std::string yaml_;
  std::unique_ptr<SimProcess> sim_;
  std::unique_ptr<GatewayProcess> gateway_;
  std::unique_ptr<ModbusClient> plc_;
  std::unique_ptr<ModbusClient> panel_;
  Motion moving_;
  std::chrono::steady_clock::time_point started_ = std::chrono::steady_clock::now();
  bool unreadable_ = false;  // hold_unreadable_by_the_machine() said so
};

TEST_P(StopRamp, AnEStopMidMoveStandsWhereTheAxisWasNotWhereTheMovesRampWouldTakeIt) {
  start();
  move_far();
  ASSERT_TRUE(panel_->write_coil(kEStopCoil, true).ok()) << log();
  expect_stopped_where_it_was(stopped(), "e-stop");
}

TEST_P(StopRamp, AnEStopDuringATimedMoveStandsWhereTheAxisWasNotWhereThePlansRampWouldTakeIt) {
  start("",
        "sync_groups:\n  - {name: arm, field: goal_position, members: [1], holding_register_start: 0, "
        "move_time: true}\n");
  move_far(true);
  ASSERT_TRUE(panel_->write_coil(kEStopCoil, true).ok()) << log();
  expect_stopped_where_it_was(stopped(), "e-stop in a timed move");
}

TEST_P(StopRamp, AWatchdogTripMidMoveStandsWhereTheAxisWas) {
  // The shortest watchdog --check-config takes here: above the bus's worst transaction
  // (2 x 2 attempts x 100 ms response timeout + wire time).
  start(watchdog("any_write", 1000));
  move_far(false, 20);  // under way before the trip, which comes 1000 ms after the goal write
  // No more writes: the watchdog trips 1000 ms after the last one.
  ASSERT_TRUE(eventually(
      [&] {
        return panel_->read_input(kBus0WatchdogState, 1).ok() &&
               panel_->read_input(kBus0WatchdogState, 1).values[0] == kTripped;
      },
      5s))
      << log();
  expect_stopped_where_it_was(stopped(), "watchdog trip");
}

TEST_P(StopRamp, AGracefulStopOfTheGatewayHoldsWhereTheAxisWas) {
  start();
  move_far();
  EXPECT_EQ(gateway_->stop(), 0) << log();
  expect_stopped_where_it_was(stopped(), "on_stop: hold");
}

TEST_P(StopRamp, AfterAKillAndARestartOnStartHoldStandsWhereTheAxisWas) {
  start(", on_start: hold");
  move_far();
  gateway_.reset();  // SIGKILL: no on_stop; the axis runs on toward its far goal meanwhile
  start_gateway();
  expect_stopped_where_it_was(stopped(), "on_start: hold after kill -9");
}

INSTANTIATE_TEST_SUITE_P(EveryTable, StopRamp, testing::ValuesIn(kCases), case_name);

}  // namespace
}  // namespace sms::e2e
