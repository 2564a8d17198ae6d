// modbus_map/motion: which writes move a servo, what a safe stop reads and writes, per table.
#include "modbus_map/motion.h"

#include <gtest/gtest.h>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

using protocol::Bytes;

// The bytes of stop_context_reads(spec) with named fields set, in the table's byte order.
class Context {
 public:
  Context(TableId table, ByteOrder order)
      : spec_(motion_spec(table)), order_(order), ranges_(stop_context_reads(spec_)) {
    for (const auto& range : ranges_) data_.emplace_back(std::size_t{range.count} * per(), 0);
  }

  Context& set(std::string_view name, std::int32_t value) {
    const FieldSpec* field = field_by_name(table(spec_.table), name);
    EXPECT_NE(field, nullptr) << name;
    return set_raw(name, encode_value(*field, value).value());
  }
  // A raw value, also one the table does not document.
  Context& set_raw(std::string_view name, std::uint32_t raw) {
    const FieldSpec* field = field_by_name(table(spec_.table), name);
    EXPECT_NE(field, nullptr) << name;
    for (std::size_t i = 0; i < ranges_.size(); ++i) {
      if (field->addr < ranges_[i].address || field->addr >= ranges_[i].end()) continue;
      const std::size_t offset = std::size_t{static_cast<std::size_t>(field->addr - ranges_[i].address)} * per();
      store_raw(std::span(data_[i]).subspan(offset, field->size), field->size, order(), raw);
      return *this;
    }
    ADD_FAILURE() << name << " is not in the context reads";
    return *this;
  }

  Expected<SafeStopPlan> plan(StopAction action, StopOptions options = {}) const {
    return plan_safe_stop(spec_, action, order_, StopContext{ranges_, data_}, options);
  }
  const std::vector<BusRange>& ranges() const { return ranges_; }

 private:
  std::size_t per() const { return bytes_per_address(table(spec_.table).addressing); }
  ByteOrder order() const {
    return table(spec_.table).addressing == Addressing::Register ? ByteOrder::HighFirst : order_;
  }

  const MotionSpec& spec_;
  ByteOrder order_;
  std::vector<BusRange> ranges_;
  std::vector<Bytes> data_;
};

WritePlan plan_of(std::uint16_t address, Bytes data) { return WritePlan{false, {BusWrite{address, std::move(data)}}}; }

TEST(Motion, EveryTableHasAMotionSpecWhoseFieldsExist) {
  for (const TableSpec* t : all_tables()) {
    const MotionSpec& spec = motion_spec(t->id);
    EXPECT_NO_THROW(stop_context_reads(spec)) << t->name;
    EXPECT_NO_THROW(goal_block(spec)) << t->name;
    EXPECT_NO_THROW(torque_off_write(spec, t->default_byte_order)) << t->name;
    for (const auto name : spec.motion_fields) EXPECT_NE(field_by_name(*t, name), nullptr) << t->name << " " << name;
    for (const auto& stop : spec.stopping_writes) EXPECT_NE(field_by_name(*t, stop.field), nullptr) << t->name;
  }
}

TEST(Motion, StopContextReadsMergeFieldsThatLieClose) {
  // mode .. present speed, the stop ramp (acceleration, 41) inside
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Sts)), (std::vector<BusRange>{{33, 27}}));
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Sms1)), (std::vector<BusRange>{{35, 25}}));
  // d55d: the angle limits (6-9) and resolution (10) merge with the goal block, both ramps and
  // the present position and speed (30-39): one READ.
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::D55d)), (std::vector<BusRange>{{6, 34}}));
  // SMSMB registers lie far apart: mode, goal block (its acceleration inside), present position and speed.
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Smsmb)), (std::vector<BusRange>{{0x10, 1}, {0x80, 4}, {0x101, 2}}));
}

TEST(Motion, HoldInPositionModeMakesThePresentPositionTheGoalAndBrakesAtTheFastestRamp) {
  Context context(TableId::Sts, ByteOrder::LowFirst);
  context.set("operating_mode", 0).set("torque_enable", 1).set("goal_position", 4000).set("goal_speed", 1200);
  context.set("acceleration", 9).set("present_position", -1523).set("present_speed", 800);
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_TRUE(plan) << plan.error();
  EXPECT_EQ(plan->drive, Drive::Position);
  // 41-47 in one write: acceleration 0 ("no ramp": the move's gentle 9 would coast the axis on
  // past its goal, then back), goal -1523 (sign-magnitude bit 15, low first), time 0, speed 1200 kept.
  ASSERT_EQ(plan->writes.size(), 1u);
  EXPECT_EQ(plan->writes[0], (BusWrite{41, {0x00, 0xF3, 0x85, 0x00, 0x00, 0xB0, 0x04}}));
  EXPECT_EQ(plan->what, "hold (position mode: goal := present position -1523, acceleration := 0)");
}

TEST(Motion, AStopDecelerationPutsTheGoalWhereTheAxisWillStandSoItNeverDrivesBack) {
  Context context(TableId::Sts, ByteOrder::LowFirst);
  context.set("operating_mode", 0).set("torque_enable", 1).set("goal_position", 4000).set("goal_speed", 60);
  context.set("present_position", 1000).set("present_speed", 40);  // 40 x 0.732 rpm = 1999 steps/s
  const auto plan = context.plan(StopAction::Hold, StopOptions{.deceleration = 50});
  ASSERT_TRUE(plan) << plan.error();
  // 1999 steps/s braked at 50 x 100 steps/s^2: v^2 / 2a = 1999^2 / 10000 = 399.5, 400 steps on.
  const std::int32_t goal = 1000 + 400;
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{41, {50, goal & 0xFF, goal >> 8, 0, 0, 60, 0}}}));
  EXPECT_EQ(plan->what, "hold (position mode: goal := present position 1000 + run-on 400 = 1400, acceleration := 50)");

  context.set("present_speed", -40);  // the other way
  const auto back = context.plan(StopAction::Hold, StopOptions{.deceleration = 50});
  ASSERT_TRUE(back) << back.error();
  EXPECT_EQ(back->writes[0].data.at(1) | (back->writes[0].data.at(2) << 8), 600);
}

TEST(Motion, D55dStopsAtBothItsRampsLargestCountWithTheRunOnInItsOwnUnits) {
  Context arm(TableId::D55d, ByteOrder::LowFirst);
  arm.set("ccw_angle_limit", 3600).set("angle_resolution", 10).set("present_position", 200);
  arm.set("run_speed", 300).set("acceleration", 2).set("deceleration", 3).set("present_speed", 300);
  const auto hold = arm.plan(StopAction::Hold);
  ASSERT_TRUE(hold) << hold.error();
  // 300 units/s at 254 x 10 units/s^2 (resolution 10: a unit is a degree): 300^2 / 5080 = 18 on.
  EXPECT_EQ(hold->writes, (std::vector<BusWrite>{{30, {218, 0, 0x2C, 0x01, 254, 254}}}));
  // A finer resolution (1: 0.1 deg a unit): the same degrees are more units, the same count of
  // 10 deg/s^2 too.
  arm.set("angle_resolution", 1).set("present_speed", 3000);  // 300 deg/s
  const auto fine = arm.plan(StopAction::Hold);
  ASSERT_TRUE(fine) << fine.error();
  const std::int32_t goal = 200 + 178;  // 3000^2 / (2 x 254 x 100) = 177.2, up to the next unit
  EXPECT_EQ(fine->writes[0].data.at(0) | (fine->writes[0].data.at(1) << 8), goal);
  // The run-on stops at the angle limit: a goal past it is one the motor never reaches.
  arm.set("ccw_angle_limit", 250);
  const auto limited = arm.plan(StopAction::Hold);
  ASSERT_TRUE(limited) << limited.error();
  EXPECT_EQ(limited->writes[0].data.at(0), 250);
}

TEST(Motion, AStopDecelerationOutsideTheRampFieldOrOnATableWithoutOneIsRefused) {
  EXPECT_FALSE(check_stop_deceleration(motion_spec(TableId::Sts), 1));
  EXPECT_FALSE(check_stop_deceleration(motion_spec(TableId::D55d), 254));
  EXPECT_TRUE(check_stop_deceleration(motion_spec(TableId::D55d), 255));
  EXPECT_TRUE(check_stop_deceleration(motion_spec(TableId::Sts), 0));
  EXPECT_TRUE(check_stop_deceleration(motion_spec(TableId::Sts), 255));
  const auto scs = check_stop_deceleration(motion_spec(TableId::Scs), 10);
  ASSERT_TRUE(scs);
  EXPECT_NE(scs->find("no acceleration field"), std::string::npos) << *scs;
}

TEST(Motion, HoldInSpeedModeWritesSpeedZeroAndInPwmModeDutyZero) {
  Context speed(TableId::Sts, ByteOrder::LowFirst);
  speed.set("operating_mode", 1).set("torque_enable", 1).set("goal_position", 100).set("goal_speed", -1500);
  const auto stop = speed.plan(StopAction::Hold);
  ASSERT_TRUE(stop) << stop.error();
  EXPECT_EQ(stop->writes, (std::vector<BusWrite>{{41, {0, 100, 0, 0, 0, 0, 0}}}));

  Context pwm(TableId::Sms1, ByteOrder::LowFirst);
  pwm.set("operating_mode", 2).set("torque_switch", 1).set("run_time", -500).set("run_speed", 0);
  const auto duty = pwm.plan(StopAction::Hold);
  ASSERT_TRUE(duty) << duty.error();
  EXPECT_EQ(duty->drive, Drive::Pwm);
  EXPECT_EQ(duty->writes, (std::vector<BusWrite>{{41, {0, 0, 0, 0, 0, 0, 0}}}));
}

TEST(Motion, HoldInStepModeSwitchesTheTorqueOffBecauseNoGoalHolds) {
  Context context(TableId::Sts, ByteOrder::LowFirst);
  context.set("operating_mode", 3).set("torque_enable", 1);
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_TRUE(plan) << plan.error();
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{40, {0}}}));
  EXPECT_NE(plan->what.find("step mode"), std::string::npos);
}

TEST(Motion, AServoWithoutTorqueIsLeftAloneUnlessItIsAboutToBeSwitchedOn) {
  Context context(TableId::Sts, ByteOrder::LowFirst);
  context.set("operating_mode", 0).set("torque_enable", 0).set("present_position", 10);
  const auto idle = context.plan(StopAction::Hold);
  ASSERT_TRUE(idle);
  EXPECT_TRUE(idle->writes.empty());
  context.set("acceleration", 9);
  const auto before_torque_on = context.plan(
      StopAction::Hold, StopOptions{.torque_known_on = true, .deceleration = std::nullopt, .keep_ramp = true});
  ASSERT_TRUE(before_torque_on);
  // The motor stands: the PLC's ramp (9) stays.
  EXPECT_EQ(before_torque_on->writes, (std::vector<BusWrite>{{41, {9, 10, 0, 0, 0, 0, 0}}}));
}

TEST(Motion, D55dSpeedModeIsBothLimitsZeroAndItsStopIsRunSpeedZero) {
  Context wheel(TableId::D55d, ByteOrder::LowFirst);
  wheel.set("cw_angle_limit", 0).set("ccw_angle_limit", 0).set("goal_position", 90).set("run_speed", 300);
  const auto stop = wheel.plan(StopAction::Hold);
  ASSERT_TRUE(stop) << stop.error();
  EXPECT_EQ(stop->drive, Drive::Velocity);
  EXPECT_EQ(stop->writes, (std::vector<BusWrite>{{30, {90, 0, 0, 0, 254, 254}}}));

  Context arm(TableId::D55d, ByteOrder::LowFirst);
  arm.set("ccw_angle_limit", 360).set("present_position", 200).set("run_speed", 300);
  const auto hold = arm.plan(StopAction::Hold);
  ASSERT_TRUE(hold) << hold.error();
  // goal 200 (standing: no run-on), speed 300 kept, both ramps their largest count
  EXPECT_EQ(hold->writes, (std::vector<BusWrite>{{30, {200, 0, 0x2C, 0x01, 254, 254}}}));
  EXPECT_EQ(torque_off_write(motion_spec(TableId::D55d), ByteOrder::LowFirst), (BusWrite{32, {0, 0}}));
}

TEST(Motion, SmsmbHoldWritesTheGoalBlockRegistersHighByteFirst) {
  Context context(TableId::Smsmb, ByteOrder::HighFirst);
  context.set("mode", 0).set("torque_switch", 1).set("acceleration", 20).set("running_speed", 500);
  context.set("goal_position", 3000).set("present_position", -2);
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_TRUE(plan) << plan.error();
  // acceleration 20 becomes 0 ("0 = maximum"), in the same write
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{0x80, {0xFF, 0xFE, 0, 1, 0, 0, 0x01, 0xF4}}}));
  const auto off = context.plan(StopAction::TorqueOff);
  ASSERT_TRUE(off);
  EXPECT_EQ(off->writes, (std::vector<BusWrite>{{0x81, {0, 0}}}));
}

TEST(Motion, AnUndocumentedModeOrAMissingReadIsAnErrorNotAGuess) {
  Context context(TableId::Smsmb, ByteOrder::HighFirst);
  context.set_raw("mode", 2).set("torque_switch", 1);  // 2 is reserved
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_FALSE(plan);
  EXPECT_NE(plan.error().find("operating mode 2"), std::string::npos);
  const auto unread = plan_safe_stop(motion_spec(TableId::Sts), StopAction::Hold, ByteOrder::LowFirst, {});
  EXPECT_FALSE(unread);
}

TEST(Motion, MotionWritesAreGoalsModeTorqueOnBrakeReleaseAndHoming) {
  const MotionSpec& sts = motion_spec(TableId::Sts);
  EXPECT_TRUE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(42, {0x10, 0x00})));      // goal position
  EXPECT_TRUE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(33, {1})));               // mode
  EXPECT_TRUE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(40, {1})));               // torque on
  EXPECT_FALSE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(40, {0})));              // torque off stops
  EXPECT_FALSE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(41, {20})));             // acceleration
  EXPECT_TRUE(motion_in_plan(sts, ByteOrder::LowFirst, plan_of(40, {0, 20, 0x10, 0})));  // torque off + goal
  const auto named = motion_in_plan(sts, ByteOrder::LowFirst, plan_of(46, {0xDC, 0x05}));
  ASSERT_TRUE(named);
  EXPECT_EQ(*named, "goal_speed (46)");

  const MotionSpec& d55d = motion_spec(TableId::D55d);
  EXPECT_FALSE(motion_in_plan(d55d, ByteOrder::LowFirst, plan_of(43, {1})));     // brake on
  EXPECT_TRUE(motion_in_plan(d55d, ByteOrder::LowFirst, plan_of(43, {0})));      // brake off resumes
  EXPECT_FALSE(motion_in_plan(d55d, ByteOrder::LowFirst, plan_of(32, {0, 0})));  // speed 0 stops
  EXPECT_TRUE(motion_in_plan(d55d, ByteOrder::LowFirst, plan_of(24, {1})));      // homing turns the motor

  const MotionSpec& smsmb = motion_spec(TableId::Smsmb);
  EXPECT_FALSE(motion_in_plan(smsmb, ByteOrder::HighFirst, plan_of(0x81, {0, 0})));
  EXPECT_TRUE(motion_in_plan(smsmb, ByteOrder::HighFirst, plan_of(0x81, {0, 1})));
}

TEST(Motion, EveryTorqueOnIsAnEnablingWriteWhateverElseTheRequestWrites) {
  const MotionSpec& sts = motion_spec(TableId::Sts);
  EXPECT_TRUE(may_enable_motion(sts, ByteOrder::LowFirst, plan_of(40, {1}).writes));
  // torque 1 with a goal position in the same request: a servo in speed mode would run its stale
  // goal speed, so this is a torque-on too.
  EXPECT_TRUE(may_enable_motion(sts, ByteOrder::LowFirst, plan_of(40, {1, 0, 0x10, 0x00}).writes));
  EXPECT_FALSE(may_enable_motion(sts, ByteOrder::LowFirst, plan_of(40, {0}).writes));
  EXPECT_FALSE(may_enable_motion(sts, ByteOrder::LowFirst, plan_of(42, {0x10, 0x00}).writes));
  // d55d has no torque switch: releasing the brake enables it (enable_fields_test.cpp).
  EXPECT_TRUE(may_enable_motion(motion_spec(TableId::D55d), ByteOrder::LowFirst, plan_of(43, {0}).writes));
}

TEST(Motion, MotionEnabledReadsTheEnableFieldsFromTheContext) {
  const MotionSpec& sts = motion_spec(TableId::Sts);
  const auto ranges = enable_context_reads(sts);
  ASSERT_EQ(ranges.size(), 1u);
  protocol::Bytes data(ranges[0].count, 0);
  const std::vector<protocol::Bytes> context{data};
  EXPECT_EQ(motion_enabled(sts, ByteOrder::LowFirst, StopContext{ranges, context}), false);
  data[40 - ranges[0].address] = 1;
  const std::vector<protocol::Bytes> on{data};
  EXPECT_EQ(motion_enabled(sts, ByteOrder::LowFirst, StopContext{ranges, on}), true);
  // The stop context of d55d does not hold its sleep and brake.
  const MotionSpec& d55d = motion_spec(TableId::D55d);
  const auto stop_ranges = stop_context_reads(d55d);
  std::vector<protocol::Bytes> stop_data;
  for (const auto& range : stop_ranges) stop_data.emplace_back(range.count, 0);
  EXPECT_EQ(motion_enabled(d55d, ByteOrder::LowFirst, StopContext{stop_ranges, stop_data}), std::nullopt);
}

}  // namespace
}  // namespace sms::modbus_map
