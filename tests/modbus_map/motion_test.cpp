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

  Expected<SafeStopPlan> plan(StopAction action, bool torque_known_on = false) const {
    return plan_safe_stop(spec_, action, order_, StopContext{ranges_, data_}, torque_known_on);
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
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Sts)), (std::vector<BusRange>{{33, 25}}));  // mode .. present
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Sms1)), (std::vector<BusRange>{{35, 23}}));
  // d55d: the angle limits (6-9) are too far from the goal block and present position (30-37).
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::D55d)), (std::vector<BusRange>{{6, 4}, {30, 8}}));
  // SMSMB registers lie far apart: mode, goal block, present position.
  EXPECT_EQ(stop_context_reads(motion_spec(TableId::Smsmb)), (std::vector<BusRange>{{0x10, 1}, {0x80, 4}, {0x101, 1}}));
}

TEST(Motion, HoldInPositionModeMakesThePresentPositionTheGoalAndKeepsTheRestOfTheBlock) {
  Context context(TableId::Sts, ByteOrder::LowFirst);
  context.set("operating_mode", 0).set("torque_enable", 1).set("goal_position", 4000).set("goal_speed", 1200);
  context.set("present_position", -1523);
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_TRUE(plan) << plan.error();
  EXPECT_EQ(plan->drive, Drive::Position);
  // 42-47: goal -1523 (sign-magnitude bit 15, low first), time 0, speed 1200 kept.
  ASSERT_EQ(plan->writes.size(), 1u);
  EXPECT_EQ(plan->writes[0], (BusWrite{42, {0xF3, 0x85, 0x00, 0x00, 0xB0, 0x04}}));
}

TEST(Motion, HoldInSpeedModeWritesSpeedZeroAndInPwmModeDutyZero) {
  Context speed(TableId::Sts, ByteOrder::LowFirst);
  speed.set("operating_mode", 1).set("torque_enable", 1).set("goal_position", 100).set("goal_speed", -1500);
  const auto stop = speed.plan(StopAction::Hold);
  ASSERT_TRUE(stop) << stop.error();
  EXPECT_EQ(stop->writes, (std::vector<BusWrite>{{42, {100, 0, 0, 0, 0, 0}}}));

  Context pwm(TableId::Sms1, ByteOrder::LowFirst);
  pwm.set("operating_mode", 2).set("torque_switch", 1).set("run_time", -500).set("run_speed", 0);
  const auto duty = pwm.plan(StopAction::Hold);
  ASSERT_TRUE(duty) << duty.error();
  EXPECT_EQ(duty->drive, Drive::Pwm);
  EXPECT_EQ(duty->writes, (std::vector<BusWrite>{{42, {0, 0, 0, 0, 0, 0}}}));
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
  const auto before_torque_on = context.plan(StopAction::Hold, true);
  ASSERT_TRUE(before_torque_on);
  EXPECT_EQ(before_torque_on->writes, (std::vector<BusWrite>{{42, {10, 0, 0, 0, 0, 0}}}));
}

TEST(Motion, D55dSpeedModeIsBothLimitsZeroAndItsStopIsRunSpeedZero) {
  Context wheel(TableId::D55d, ByteOrder::LowFirst);
  wheel.set("cw_angle_limit", 0).set("ccw_angle_limit", 0).set("goal_position", 90).set("run_speed", 300);
  const auto stop = wheel.plan(StopAction::Hold);
  ASSERT_TRUE(stop) << stop.error();
  EXPECT_EQ(stop->drive, Drive::Velocity);
  EXPECT_EQ(stop->writes, (std::vector<BusWrite>{{30, {90, 0, 0, 0}}}));

  Context arm(TableId::D55d, ByteOrder::LowFirst);
  arm.set("ccw_angle_limit", 360).set("present_position", 200).set("run_speed", 300);
  const auto hold = arm.plan(StopAction::Hold);
  ASSERT_TRUE(hold) << hold.error();
  EXPECT_EQ(hold->writes, (std::vector<BusWrite>{{30, {200, 0, 0x2C, 0x01}}}));  // goal 200, speed 300 kept
  EXPECT_EQ(torque_off_write(motion_spec(TableId::D55d), ByteOrder::LowFirst), (BusWrite{32, {0, 0}}));
}

TEST(Motion, SmsmbHoldWritesTheGoalBlockRegistersHighByteFirst) {
  Context context(TableId::Smsmb, ByteOrder::HighFirst);
  context.set("mode", 0).set("torque_switch", 1).set("acceleration", 20).set("running_speed", 500);
  context.set("goal_position", 3000).set("present_position", -2);
  const auto plan = context.plan(StopAction::Hold);
  ASSERT_TRUE(plan) << plan.error();
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{0x80, {0xFF, 0xFE, 0, 1, 0, 20, 0x01, 0xF4}}}));
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
