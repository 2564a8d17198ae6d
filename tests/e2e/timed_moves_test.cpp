// Timed group moves (docs/PLC_GUIDE.md "Timed group moves"): a PLC writes goals and a move time
// to a sync group, and every axis arrives together, at that time. The real sms-gateway on the real
// sms-sim, whose motor model ramps and runs at the speed and acceleration written; the witness is
// the simulator's own record of when each goal was written and when its motor reached it.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
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

constexpr int kAxes = 6;
constexpr int kPollPeriodMs = 20;
constexpr int kMoveTimeRegister = kAxes;  // after the six goals
constexpr int kStretchGroupStart = 10;    // the same axes, `stretch: true`
constexpr int kGroupInputs = 2000;        // group 0's input registers; group 1's at 2010
constexpr int kStart = 500;               // where every axis starts
constexpr std::array<int, kAxes> kDistances{100, 600, 1200, 1800, 2400, 3000};

// Input registers of a group (docs/PLC_GUIDE.md "Timed group moves").
enum GroupInput { kMoving = 0, kTimeLeft = 1, kToGo = 2, kLastMove = 3, kLimitingUnit = 4, kShortest = 5, kUsed = 6 };

// Response timeout 500 ms: the test command's first minute (Chromium starting beside six
// sanitizer suites and the compile lanes) held simulators 170-575 ms; these tests are about
// moves, and a servo taken offline by such a stall would refuse their writes. d55d stays at
// 100 ms: its motors stop themselves after 500 ms without an instruction (their heartbeat), and
// two 500 ms attempts to one motor would leave the others that long.
std::string config(const std::string& pty, const std::string& bus_protocol, const std::string& table, int baud,
                   const std::string& bus_extra) {
  std::string yaml = "buses:\n  - {name: arm, device: \"" + pty + "\", protocol: " + bus_protocol +
                     ", baud: " + std::to_string(baud) + ", poll_period_ms: " + std::to_string(kPollPeriodMs) +
                     ", response_timeout_ms: " + (bus_protocol == "d55d" ? "100" : "500") + ", retries: 1" + bus_extra +
                     "}\nservos:\n";
  for (int id = 1; id <= kAxes; ++id) {
    yaml += "  - {unit: " + std::to_string(id) + ", bus: arm, id: " + std::to_string(id) + ", table: " + table + "}\n";
  }
  const std::string members = "[1, 2, 3, 4, 5, 6]";
  yaml += "sync_groups:\n  - {name: arm, field: goal_position, members: " + members +
          ", holding_register_start: 0, move_time: true}\n"
          "  - {name: arm_stretched, field: goal_position, members: " +
          members + ", holding_register_start: " + std::to_string(kStretchGroupStart) +
          ", move_time: true, stretch: true}\n";
  return yaml;
}

class Arm {
 public:
  // `bus_extra`: more keys of the bus (", poll_fields: [...]").
  explicit Arm(const std::string& table = "sts", const std::string& sim_protocol = "feetech",
               const std::string& bus_protocol = "feetech", int baud = 1000000, const std::string& bus_extra = "")
      : sim_(dir_, "arm", servos(table, sim_protocol, baud)),
        gateway_(GatewayProcess::with_config(dir_, config(sim_.pty(), bus_protocol, table, baud, bus_extra), 1)),
        plc_(gateway_.port(), kGateway) {
    for (int unit = 1; unit <= kAxes; ++unit) wait_until_polled(gateway_.port(), unit);
  }

  SimProcess& sim() { return sim_; }
  std::uint16_t port() const { return gateway_.port(); }
  ModbusClient& plc() { return plc_; }
  std::string log() { return gateway_.process().output(); }

  // Every axis to `start` in a timed move of 2 s (d55d runs nowhere at its power-on run speed 0),
  // the move time back to 0, and waits until all are there.
  // A d55d motor stops itself after 500 ms without an instruction (its heartbeat): where the
  // simulator witnessed that (a loaded machine held the gateway's bus thread that long), the move
  // is sent again, at most three times.
  void home(int start = kStart) {
    std::vector<std::uint16_t> values(kAxes, static_cast<std::uint16_t>(start));
    values.push_back(2000);
    const auto heartbeat_stops = [&] {
      long stops = 0;
      for (int id = 1; id <= kAxes; ++id) stops += motion_of(sim_, id).heartbeat_stops;
      return stops;
    };
    const auto all_there = [&] {
      for (int id = 1; id <= kAxes; ++id) {
        const Motion motion = motion_of(sim_, id);
        if (motion.position != start || motion.arrived_us < 0) return false;
      }
      return true;
    };
    std::string where;
    for (int attempt = 0; attempt < 3; ++attempt) {
      const long stops_before = heartbeat_stops();
      ASSERT_TRUE(plc_.write_registers(0, values).ok()) << log();
      ASSERT_TRUE(plc_.write_register(kMoveTimeRegister, 0).ok()) << log();
      if (eventually(all_there, 10s)) return wait_cache_standing();
      if (heartbeat_stops() == stops_before) break;
    }
    for (int id = 1; id <= kAxes; ++id) {
      const Motion motion = motion_of(sim_, id);
      where += " axis " + std::to_string(id) + " at " + std::to_string(motion.position) + " (arrived " +
               std::to_string(motion.arrived_us) + ", heartbeat stops " + std::to_string(motion.heartbeat_stops) + ")";
    }
    FAIL() << "the axes never got to " << start << ":" << where << "\n" << log();
  }
  void wait_cache_standing() {
    // And the gateway's poll cache has seen them stand there: a timed move plans from it.
    ASSERT_TRUE(eventually([&] { return group_inputs(0)[kToGo] == 0; })) << log();
  }

  std::vector<std::uint16_t> group_inputs(int group) {
    return plc_.read_input(kGroupInputs + 10 * group, 7).or_throw("group input registers");
  }

  // Waits until every axis has reached `goals` on a goal written after `after_us`; their records.
  // `report`: a failure where they did not (else the caller decides).
  std::vector<Motion> arrivals(const std::vector<std::uint16_t>& goals, long long after_us, bool report = true) {
    std::vector<Motion> motions(kAxes);
    const bool arrived = eventually(
        [&] {
          for (int id = 1; id <= kAxes; ++id) {
            motions[id - 1] = motion_of(sim_, id);
            const Motion& m = motions[id - 1];
            if (m.started_us <= after_us || m.arrived_us < 0 || m.position != goals[id - 1]) return false;
          }
          return true;
        },
        20s);
    if (!arrived) {
      if (report) ADD_FAILURE() << "the axes did not all reach their goals\n" << log();
      return {};
    }
    return motions;
  }

 private:
  static std::vector<std::string> servos(const std::string& table, const std::string& protocol, int baud) {
    std::vector<std::string> args;
    for (int id = 1; id <= kAxes; ++id) {
      args.insert(args.end(),
                  {"--servo", std::to_string(id) + ":" + table + ":" + protocol + ":" + std::to_string(baud)});
    }
    return args;
  }

  TempDir dir_;
  SimProcess sim_;
  GatewayProcess gateway_;
  ModbusClient plc_;
};

long long now_us() {
  return std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::vector<std::uint16_t> goals_for(const std::array<int, kAxes>& distances, int start = kStart) {
  std::vector<std::uint16_t> goals;
  for (const int distance : distances) goals.push_back(static_cast<std::uint16_t>(start + distance));
  return goals;
}

// What the spread of arrivals is measured on: the arrivals themselves when one SYNC WRITE starts
// every axis at once; each axis's time from its own goal when a modbus-rtu bus writes the goals one
// after another (how far apart those go out is the bus's and the machine's, not the plan's).
enum class Spread { Arrivals, MoveTimes };

// The spread of the arrivals and each axis's time from its goal to its arrival, against `ms`.
void expect_together_at(const std::vector<Motion>& motions, int ms, Spread spread = Spread::Arrivals) {
  std::vector<long long> ends;
  for (const Motion& motion : motions) {
    ends.push_back(spread == Spread::Arrivals ? motion.arrived_us : motion.arrived_us - motion.started_us);
  }
  const auto [first, last] = std::minmax_element(ends.begin(), ends.end());
  EXPECT_LE(*last - *first, 2 * kPollPeriodMs * 1000) << "arrivals spread over more than 2 polls";
  for (std::size_t axis = 0; axis < motions.size(); ++axis) {
    const double took_ms = (motions[axis].arrived_us - motions[axis].started_us) / 1000.0;
    EXPECT_NEAR(took_ms, ms, 0.05 * ms) << "axis " << axis + 1 << " took " << took_ms << " ms";
  }
}

void timed_move_arrives_together(Arm& arm, Spread spread = Spread::Arrivals, int start = kStart,
                                 const std::array<int, kAxes>& distances = kDistances) {
  // A move the machine held the simulator through (half a second: a d55d motor's heartbeat stops
  // it, a poll comes too late to plan from) is made again, at most three times, where the
  // simulator witnessed the hold (tests/README.md "Counting on a loaded machine").
  std::vector<Motion> motions;
  for (int attempt = 1; motions.empty(); ++attempt) {
    arm.home(start);
    const auto sent = std::chrono::steady_clock::now();
    const long long before = now_us();
    std::vector<std::uint16_t> request = goals_for(distances, start);
    request.push_back(1500);  // the move time, in the same FC16
    const auto answer = arm.plc().write_registers(0, request);
    ASSERT_TRUE(answer.ok()) << answer.error << "\n" << arm.log();
    const bool held = [&] {
      motions = arm.arrivals(goals_for(distances, start), before, false);
      return sim_held(arm.sim(), 400ms, sent);
    }();
    if (!motions.empty() && !held) break;
    if (!held || attempt == 3) {
      if (motions.empty()) FAIL() << "the axes did not all reach their goals\n" << arm.log();
      break;
    }
    std::cout << "attempt " << attempt << ": the machine held the simulator (" << arm.sim().control("holds")
              << "); the move is made again\n";
    motions.clear();
  }
  expect_together_at(motions, 1500, spread);
  const auto inputs = arm.group_inputs(0);
  EXPECT_EQ(inputs[kLastMove], 1);  // as asked
  EXPECT_EQ(inputs[kUsed], 1500);
  EXPECT_EQ(inputs[kLimitingUnit], 6);  // the longest way
  EXPECT_LT(inputs[kShortest], 1500);
  EXPECT_TRUE(eventually([&] { return arm.group_inputs(0)[kMoving] == 0; }));
  EXPECT_TRUE(eventually([&] { return arm.group_inputs(0)[kToGo] == 0; }));
}

TEST(TimedMoves, SixStsAxesArriveTogetherAtTheMoveTime) {
  Arm arm;
  timed_move_arrives_together(arm);
}

// The other feetech tables: sms1 (its own speed and ramp units) and scs (no ramp, 0-1023).
TEST(TimedMoves, SixSms1AxesArriveTogetherAtTheMoveTime) {
  Arm arm("sms1");
  timed_move_arrives_together(arm);
}

TEST(TimedMoves, SixScsAxesArriveTogetherAtTheMoveTime) {
  Arm arm("scs");
  timed_move_arrives_together(arm, Spread::Arrivals, 100, {50, 150, 300, 450, 600, 800});
}

// SMSMB servos on a modbus-rtu bus: no SYNC WRITE, so one write per servo (speeds first, then goals).
TEST(TimedMoves, SixSmsmbAxesOnModbusRtuArriveTogether) {
  Arm arm("smsmb", "modbus-rtu", "modbus-rtu", 115200);
  timed_move_arrives_together(arm, Spread::MoveTimes);
}

// d55d motors in position mode (360° at the default resolution, 1° a position unit): goal, run
// speed, acceleration and deceleration in one SYNC WRITE block (30-35).
TEST(TimedMoves, SixD55dAxesArriveTogether) {
  Arm arm("d55d", "d55d", "d55d", 115200);
  timed_move_arrives_together(arm, Spread::Arrivals, 20, {10, 60, 120, 180, 240, 300});
}

// A d55d motor in wheel mode (both angle limits 0) takes relative goals: no distance to plan.
TEST(TimedMoves, AD55dInWheelModeRefusesTheMove) {
  Arm arm("d55d", "d55d", "d55d", 115200);
  arm.home(20);
  ASSERT_EQ(arm.sim().control("set 6 6 00 00 00 00"), "ok");  // unit 6: cw and ccw limits 0
  const long long started_before = motion_of(arm.sim(), 1).started_us;
  std::vector<std::uint16_t> request = goals_for({10, 60, 120, 180, 240, 300}, 20);
  request.push_back(1500);
  // A move refused 0x0B (a servo offline a moment while the machine held the simulator: the
  // planning read is answered so) is asked again once every axis is polled, at most three times.
  int exception = 0;
  for (int attempt = 1; attempt <= 3; ++attempt) {
    exception = arm.plc().write_registers(0, request).exception;
    if (exception != 0x0B || !sim_held(arm.sim(), 100ms, std::chrono::steady_clock::now() - 5s)) break;
    for (int unit = 1; unit <= kAxes; ++unit) wait_until_polled(arm.port(), unit);
  }
  EXPECT_EQ(exception, 3);
  EXPECT_EQ(motion_of(arm.sim(), 1).started_us, started_before) << "an axis was given its goal";
  EXPECT_EQ(arm.sim().field(1, "goal_position"), 20);
}

// A bus that does not poll present positions: the gateway reads each axis's before planning.
TEST(TimedMoves, PresentPositionsOutsideTheCacheAreReadLive) {
  Arm arm("sts", "feetech", "feetech", 1000000, ", poll_fields: [present_load]");
  timed_move_arrives_together(arm);
}

// The move time register is a write like any other for the watchdog (feed any_write): carried
// out, it feeds; a refused timed move does not.
TEST(TimedMoves, AMoveTimeWriteFeedsTheWatchdogARefusedMoveDoesNot) {
  Arm arm("sts", "feetech", "feetech", 1000000, ", watchdog: {timeout_ms: 60000, feed: any_write}");
  constexpr int kBus0SinceFeed = 111;  // ms since the last feed; 65535: never
  const auto since_feed = [&] { return arm.plc().read_input(kBus0SinceFeed, 1).or_throw("since feed")[0]; };
  ASSERT_EQ(since_feed(), 0xFFFF);
  std::vector<std::uint16_t> request = goals_for(kDistances);
  request.push_back(100);  // too short: refused, nothing carried out
  EXPECT_EQ(arm.plc().write_registers(0, request).exception, 3);
  EXPECT_EQ(since_feed(), 0xFFFF);
  ASSERT_TRUE(arm.plc().write_register(kMoveTimeRegister, 1500).ok()) << arm.log();
  EXPECT_NE(since_feed(), 0xFFFF);
}

TEST(TimedMoves, TheMoveTimeWrittenBeforeTheGoalsCounts) {
  Arm arm;
  arm.home();
  ASSERT_TRUE(arm.plc().write_register(kMoveTimeRegister, 1500).ok()) << arm.log();
  EXPECT_EQ(arm.plc().read_holding(kMoveTimeRegister, 1).or_throw("move time")[0], 1500);
  const long long before = now_us();
  const auto goals = goals_for(kDistances);
  ASSERT_TRUE(arm.plc().write_registers(0, goals).ok()) << arm.log();
  expect_together_at(arm.arrivals(goals, before), 1500);
}

TEST(TimedMoves, ATimeTooShortIsRefusedAndNothingIsWritten) {
  Arm arm;
  arm.home();
  std::vector<Motion> before;
  for (int id = 1; id <= kAxes; ++id) before.push_back(motion_of(arm.sim(), id));
  std::vector<std::uint16_t> request = goals_for(kDistances);
  request.push_back(300);  // 3000 steps take the servo 855 ms at best
  const auto answer = arm.plc().write_registers(0, request);
  EXPECT_EQ(answer.exception, 3) << "a move time no axis can make is an illegal value";
  for (int id = 1; id <= kAxes; ++id) {
    const Motion now = motion_of(arm.sim(), id);
    EXPECT_EQ(now.started_us, before[id - 1].started_us) << "axis " << id << " was given a goal";
    EXPECT_EQ(arm.sim().field(id, "goal_position"), kStart) << "axis " << id;
  }
  const auto inputs = arm.group_inputs(0);
  EXPECT_EQ(inputs[kLastMove], 3);  // refused
  EXPECT_EQ(inputs[kLimitingUnit], 6);
  EXPECT_GT(inputs[kShortest], 300);
  EXPECT_LT(inputs[kShortest], 1000);
  EXPECT_EQ(inputs[kMoving], 0);
  // The refused write kept no move time.
  EXPECT_EQ(arm.plc().read_holding(kMoveTimeRegister, 1).or_throw("move time")[0], 0);
}

TEST(TimedMoves, AStretchingGroupTakesTheSlowestAxisTime) {
  Arm arm;
  arm.home();
  const long long before = now_us();
  std::vector<std::uint16_t> request = goals_for(kDistances);
  request.push_back(300);
  const auto answer = arm.plc().write_registers(kStretchGroupStart, request);
  ASSERT_TRUE(answer.ok()) << answer.error << "\n" << arm.log();
  const auto inputs = arm.group_inputs(1);
  EXPECT_EQ(inputs[kLastMove], 2);  // stretched
  EXPECT_EQ(inputs[kLimitingUnit], 6);
  EXPECT_EQ(inputs[kUsed], inputs[kShortest]);
  EXPECT_GT(inputs[kUsed], 300);
  expect_together_at(arm.arrivals(goals_for(kDistances), before), inputs[kUsed]);
}

TEST(TimedMoves, AnEStopInTheMiddleStopsEveryAxis) {
  Arm arm;
  arm.home();
  std::vector<std::uint16_t> request = goals_for(kDistances);
  request.push_back(2400);  // the longest the 100-step axis can take is 2501 ms
  ASSERT_TRUE(arm.plc().write_registers(0, request).ok()) << arm.log();
  // Under way: every axis has left its start.
  ASSERT_TRUE(eventually([&] {
    for (int id = 1; id <= kAxes; ++id) {
      if (motion_of(arm.sim(), id).position == kStart) return false;
    }
    return true;
  }));
  EXPECT_EQ(arm.group_inputs(0)[kMoving], 1);
  ASSERT_TRUE(arm.plc().write_coil(kEStopCoil, true).ok()) << arm.log();
  // Every axis stands short of its goal, and stays there.
  EXPECT_TRUE(eventually([&] {
    for (int id = 1; id <= kAxes; ++id) {
      if (arm.sim().field(id, "moving") != 0) return false;
    }
    return true;
  }));
  for (int id = 1; id <= kAxes; ++id) {
    const Motion stopped = motion_of(arm.sim(), id);
    EXPECT_LT(stopped.position, kStart + kDistances[id - 1]) << "axis " << id << " went on to its goal";
  }
  const auto inputs = arm.group_inputs(0);
  EXPECT_EQ(inputs[kMoving], 0);
  EXPECT_EQ(inputs[kTimeLeft], 0);
  EXPECT_GT(inputs[kToGo], 0);
  // While latched, a timed move is refused like every motion write (0x04), nothing written, and
  // the group says so: every refusal is result 3, not the last move's 1.
  EXPECT_EQ(inputs[kLastMove], 1);
  request.back() = 1500;
  EXPECT_EQ(arm.plc().write_registers(0, request).exception, 4);
  EXPECT_EQ(arm.group_inputs(0)[kLastMove], 3);
  ASSERT_TRUE(arm.plc().write_coil(kEStopCoil, false).ok());
}

TEST(TimedMoves, AGoalOutsideAnAxissAngleLimitsIsRefusedAndNothingIsWritten) {
  Arm arm;
  arm.home();
  // Axis 1 limited to 0..3000 (the simulator's backdoor: EEPROM as commissioned).
  ASSERT_EQ(arm.sim().control("set 1 11 B8 0B"), "ok");
  const long long before = motion_of(arm.sim(), 1).started_us;
  std::vector<std::uint16_t> request = goals_for(kDistances);
  request[0] = 3500;  // past its limit: it would stop at 3000 and never arrive
  request.push_back(3000);
  EXPECT_EQ(arm.plc().write_registers(0, request).exception, 3) << arm.log();
  EXPECT_EQ(motion_of(arm.sim(), 1).started_us, before) << "an axis was given its goal";
  for (int id = 1; id <= kAxes; ++id) EXPECT_EQ(arm.sim().field(id, "goal_position"), kStart) << "axis " << id;
  EXPECT_EQ(arm.group_inputs(0)[kLastMove], 3);
  EXPECT_TRUE(eventually([&] {
    return arm.log().find("goal 3500 is outside its angle limits 0..3000") != std::string::npos;
  })) << arm.log();
  // Inside them, the same move goes.
  request[0] = 2900;
  EXPECT_TRUE(arm.plc().write_registers(0, request).ok()) << arm.log();
  EXPECT_EQ(arm.group_inputs(0)[kLastMove], 1);
}

TEST(TimedMoves, ATimeLongerThanAShortAxisCanTakeIsRefusedWithTheLongestItCan) {
  Arm arm;
  arm.home();
  std::vector<std::uint16_t> request(kAxes, kStart);
  request[1] = kStart + 10;  // 10 steps: even one count of speed and acceleration takes 0.63 s
  request.push_back(10000);
  EXPECT_EQ(arm.plc().write_registers(0, request).exception, 3) << arm.log();
  EXPECT_EQ(arm.sim().field(2, "goal_position"), kStart) << "nothing written";
  const auto inputs = arm.group_inputs(0);
  EXPECT_EQ(inputs[kLastMove], 3);
  EXPECT_EQ(inputs[kLimitingUnit], 2);
  EXPECT_GT(inputs[kUsed], 0) << "the longest time unit 2 can take";
  EXPECT_LT(inputs[kUsed], 2000);
  // A time it can take goes, and is met.
  request.back() = inputs[kUsed];
  const long long after = now_us();
  ASSERT_TRUE(arm.plc().write_registers(0, request).ok()) << arm.log();
  Motion moved;
  ASSERT_TRUE(eventually([&] {
    moved = motion_of(arm.sim(), 2);
    return moved.started_us > after && moved.arrived_us >= 0 && moved.position == kStart + 10;
  })) << arm.log();
  const double took_ms = (moved.arrived_us - moved.started_us) / 1000.0;
  EXPECT_NEAR(took_ms, inputs[kUsed], 0.05 * inputs[kUsed]);
}

TEST(TimedMoves, AMoveWhereNoAxisMovesIsNotMovingForItsWholeTime) {
  Arm arm;
  arm.home();
  std::vector<std::uint16_t> request(kAxes, kStart);
  // A plan of 60 s, six times the wait's bound: a "moving" that followed the plan, not the axes,
  // could not read 0 within the wait, whatever the machine's timing.
  request.push_back(60000);
  ASSERT_TRUE(arm.plc().write_registers(0, request).ok()) << arm.log();
  // Every axis is where its goal is: the move is over as soon as the cache shows it.
  std::vector<std::uint16_t> inputs;
  ASSERT_TRUE(eventually([&] {
    inputs = arm.group_inputs(0);
    return inputs[kMoving] == 0;
  })) << "moving read 1 while no axis moved";
  for (int id = 1; id <= kAxes; ++id) EXPECT_EQ(motion_of(arm.sim(), id).position, kStart) << "axis " << id;
  EXPECT_EQ(inputs[kTimeLeft], 0);
  EXPECT_EQ(inputs[kLastMove], 1);
}

}  // namespace
}  // namespace sms::e2e
