// "No jump on enable" as table data (modbus_map/motion.h): which writes of every table enable
// motion, and the hold plan_enable_hold makes of a servo's state and the request's writes.
#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "modbus_map/motion.h"
#include "modbus_map/register_map_doc.h"
#include "modbus_map/tables.h"
#include "tests/modbus_map/doc_text.h"

namespace sms::modbus_map {
namespace {

using protocol::Bytes;

// The bytes of enable_context_reads(spec) with named fields set, in the table's byte order.
class State {
 public:
  explicit State(TableId id) : spec_(motion_spec(id)), ranges_(enable_context_reads(spec_)) {
    for (const auto& range : ranges_) data_.emplace_back(std::size_t{range.count} * per(), 0);
  }

  State& set(std::string_view name, std::int32_t value) {
    const FieldSpec* field = field_by_name(table(spec_.table), name);
    EXPECT_NE(field, nullptr) << name;
    for (std::size_t i = 0; i < ranges_.size(); ++i) {
      if (field->addr < ranges_[i].address || field->addr >= ranges_[i].end()) continue;
      const std::size_t offset = std::size_t{static_cast<std::size_t>(field->addr - ranges_[i].address)} * per();
      store_raw(std::span(data_[i]).subspan(offset, field->size), field->size, order(),
                encode_value(*field, value).value());
      return *this;
    }
    ADD_FAILURE() << name << " is not in the enable context reads";
    return *this;
  }

  // One request's write of `name` := value (the bus bytes a plan would carry).
  BusWrite write(std::string_view name, std::int32_t value) const {
    const FieldSpec* field = field_by_name(table(spec_.table), name);
    EXPECT_NE(field, nullptr) << name;
    Bytes data(field->size, 0);
    store_raw(data, field->size, order(), encode_value(*field, value).value());
    return BusWrite{field->addr, data};
  }

  Expected<std::optional<SafeStopPlan>> hold(std::vector<BusWrite> writes) const {
    return plan_enable_hold(spec_, order(), StopContext{ranges_, data_}, writes);
  }
  std::optional<bool> enabled() const { return motion_enabled(spec_, order(), StopContext{ranges_, data_}); }

 private:
  std::size_t per() const { return bytes_per_address(table(spec_.table).addressing); }
  ByteOrder order() const { return table(spec_.table).default_byte_order; }

  const MotionSpec& spec_;
  std::vector<BusRange> ranges_;
  std::vector<Bytes> data_;
};

struct Expected_ {
  TableId table;
  std::vector<std::pair<std::string_view, std::int32_t>> enables;
  std::vector<std::string_view> drive;
};

// What each table's documents say lets its motor drive (docs/PROTOCOL.md §2).
const std::vector<Expected_> kEveryTable{
    {TableId::Sts, {{"torque_enable", 1}}, {"operating_mode"}},
    {TableId::Sms1, {{"torque_switch", 1}}, {"operating_mode"}},
    {TableId::D55d, {{"sleep", 0}, {"brake", 0}}, {"cw_angle_limit", "ccw_angle_limit"}},
    {TableId::Smsmb, {{"torque_switch", 1}}, {"mode"}},
    {TableId::Scs, {{"torque_enable", 1}}, {"min_angle_limit", "max_angle_limit"}},
};

TEST(EnableFields, EveryTableNamesWhatEnablesItsMotor) {
  ASSERT_EQ(kEveryTable.size(), all_tables().size()) << "a table without an entry here";
  for (const Expected_& expected : kEveryTable) {
    const MotionSpec& spec = motion_spec(expected.table);
    const TableSpec& t = table(expected.table);
    std::vector<std::pair<std::string_view, std::int32_t>> enables;
    for (const EnableField& enable : spec.enables) enables.emplace_back(enable.field, enable.on);
    EXPECT_EQ(enables, expected.enables) << t.name;
    EXPECT_EQ(drive_fields(spec), expected.drive) << t.name;
  }
}

TEST(EnableFields, AreWritableMotionFieldsWhoseEnablingValueIsNoStop) {
  for (const TableSpec* t : all_tables()) {
    const MotionSpec& spec = motion_spec(t->id);
    for (const EnableField& enable : spec.enables) {
      const FieldSpec* field = field_by_name(*t, enable.field);
      ASSERT_NE(field, nullptr) << t->name << " " << enable.field;
      EXPECT_NE(field->access, Access::ReadOnly) << t->name << " " << enable.field;
      EXPECT_TRUE(encode_value(*field, enable.on)) << t->name << " " << enable.field;
      EXPECT_FALSE(enable.what.empty()) << t->name << " " << enable.field;
      // Enabling is a motion write (refused while the e-stop is latched), never a stop.
      EXPECT_TRUE(is_motion_field(spec, enable.field)) << t->name << " " << enable.field;
      EXPECT_FALSE(
          std::any_of(spec.stopping_writes.begin(), spec.stopping_writes.end(),
                      [&](const StoppingWrite& stop) { return stop.field == enable.field && stop.value == enable.on; }))
          << t->name << " " << enable.field;
      // The gateway reads it before an enabling write.
      const auto reads = enable_context_reads(spec);
      EXPECT_TRUE(std::any_of(reads.begin(), reads.end(),
                              [&](const BusRange& range) {
                                return range.contains(BusRange{field->addr, address_span(t->addressing, *field)});
                              }))
          << t->name << " " << enable.field;
    }
    for (const std::string_view name : drive_fields(spec)) {
      EXPECT_TRUE(is_motion_field(spec, name)) << t->name << " " << name;
    }
  }
}

TEST(EnableFields, EnableContextReadsAddOnlyTheEnableFieldsToTheStopContext) {
  // d55d: sleep (47) and brake (43) extend the one read of the limits, resolution, goal block
  // with both ramps, and the present position and speed.
  EXPECT_EQ(enable_context_reads(motion_spec(TableId::D55d)), (std::vector<BusRange>{{6, 42}}));
  // The torque switches are in the stop context already.
  for (const TableId id : {TableId::Sts, TableId::Sms1, TableId::Smsmb, TableId::Scs}) {
    EXPECT_EQ(enable_context_reads(motion_spec(id)), stop_context_reads(motion_spec(id))) << table(id).name;
  }
}

TEST(EnableFields, WhichWritesMayEnableMotion) {
  const State sts(TableId::Sts);
  const MotionSpec& s = motion_spec(TableId::Sts);
  const auto may = [](const MotionSpec& spec, ByteOrder order, std::vector<BusWrite> writes) {
    return may_enable_motion(spec, order, writes);
  };
  EXPECT_TRUE(may(s, ByteOrder::LowFirst, {sts.write("torque_enable", 1)}));
  EXPECT_FALSE(may(s, ByteOrder::LowFirst, {sts.write("torque_enable", 0)}));
  EXPECT_FALSE(may(s, ByteOrder::LowFirst, {sts.write("torque_enable", 2)}));    // damping
  EXPECT_FALSE(may(s, ByteOrder::LowFirst, {sts.write("torque_enable", 128)}));  // calibration
  EXPECT_TRUE(may(s, ByteOrder::LowFirst, {sts.write("operating_mode", 1)}));
  EXPECT_FALSE(may(s, ByteOrder::LowFirst, {sts.write("goal_position", 100)}));  // the command itself
  EXPECT_TRUE(may(s, ByteOrder::LowFirst, {BusWrite{40, {1, 0, 0x10, 0x00}}}));  // torque 1 and a goal

  const State d55d(TableId::D55d);
  const MotionSpec& d = motion_spec(TableId::D55d);
  EXPECT_TRUE(may(d, ByteOrder::LowFirst, {d55d.write("sleep", 0)}));
  EXPECT_FALSE(may(d, ByteOrder::LowFirst, {d55d.write("sleep", 1)}));
  EXPECT_TRUE(may(d, ByteOrder::LowFirst, {d55d.write("brake", 0)}));
  EXPECT_FALSE(may(d, ByteOrder::LowFirst, {d55d.write("brake", 1)}));
  EXPECT_TRUE(may(d, ByteOrder::LowFirst, {d55d.write("cw_angle_limit", 0)}));
  EXPECT_TRUE(may(d, ByteOrder::LowFirst, {BusWrite{6, {0, 0, 0, 0}}}));  // both limits
  EXPECT_FALSE(may(d, ByteOrder::LowFirst, {d55d.write("run_speed", 90)}));
  EXPECT_FALSE(may(d, ByteOrder::LowFirst, {d55d.write("acceleration", 20)}));

  const State smsmb(TableId::Smsmb);
  const MotionSpec& m = motion_spec(TableId::Smsmb);
  EXPECT_TRUE(may(m, ByteOrder::HighFirst, {smsmb.write("torque_switch", 1)}));
  EXPECT_FALSE(may(m, ByteOrder::HighFirst, {smsmb.write("torque_switch", 0)}));
  EXPECT_TRUE(may(m, ByteOrder::HighFirst, {smsmb.write("mode", 1)}));
}

TEST(EnableFields, D55dWakingOrReleasingTheBrakeInWheelModeWritesSpeedZeroFirst) {
  for (const char* field : {"sleep", "brake"}) {
    State state(TableId::D55d);
    state.set("cw_angle_limit", 0).set("ccw_angle_limit", 0).set("goal_position", 30).set("run_speed", 90);
    state.set(field, 1);
    EXPECT_EQ(state.enabled(), false) << field;
    const auto hold = state.hold({state.write(field, 0)});
    ASSERT_TRUE(hold) << hold.error();
    ASSERT_TRUE(*hold) << field << ": no hold";
    EXPECT_EQ((*hold)->writes, (std::vector<BusWrite>{{30, {30, 0, 0, 0, 0, 0}}})) << field;  // goal kept, speed 0
    EXPECT_EQ((*hold)->drive, Drive::Velocity);
    EXPECT_NE((*hold)->what.find(std::string_view(field) == "sleep" ? "wake: hold (speed mode: speed := 0)"
                                                                    : "brake release: hold (speed mode"),
              std::string::npos)
        << (*hold)->what;
  }
}

TEST(EnableFields, D55dReleasingABrakedPositionMoveHoldsThePresentPosition) {
  State state(TableId::D55d);
  state.set("cw_angle_limit", 0).set("ccw_angle_limit", 3600).set("goal_position", 300).set("run_speed", 90);
  state.set("present_position", 150).set("brake", 1);
  const auto hold = state.hold({state.write("brake", 0)});
  ASSERT_TRUE(hold) << hold.error();
  ASSERT_TRUE(*hold);
  EXPECT_EQ((*hold)->writes, (std::vector<BusWrite>{{30, {150, 0, 90, 0, 0, 0}}}));  // goal := 150, speed 90 kept
}

TEST(EnableFields, D55dWritesThatLeaveTheMotorStoppedOrDrivingGetNoHold) {
  State awake(TableId::D55d);
  awake.set("cw_angle_limit", 0).set("ccw_angle_limit", 0).set("run_speed", 90);
  // Neither asleep nor braked: releasing again cancels nothing of the turn under way.
  for (const char* field : {"sleep", "brake"}) {
    const auto hold = awake.hold({awake.write(field, 0)});
    ASSERT_TRUE(hold) << hold.error();
    EXPECT_FALSE(*hold) << field;
  }
  // Asleep and braked: waking alone leaves it braked (the release will get the hold).
  State both(TableId::D55d);
  both.set("cw_angle_limit", 0).set("ccw_angle_limit", 0).set("run_speed", 90).set("sleep", 1).set("brake", 1);
  const auto wake = both.hold({both.write("sleep", 0)});
  ASSERT_TRUE(wake) << wake.error();
  EXPECT_FALSE(*wake);
  // Both in one request (FC15 over 43..47): one hold, both named.
  const auto release = both.hold({both.write("brake", 0), both.write("sleep", 0)});
  ASSERT_TRUE(release && *release);
  EXPECT_NE((*release)->what.find("wake, brake release: hold"), std::string::npos) << (*release)->what;
}

TEST(EnableFields, D55dAngleLimitsThatSwitchTheDriveOfARunningMotorNeutraliseTheGoalBlock) {
  State position(TableId::D55d);
  position.set("cw_angle_limit", 0).set("ccw_angle_limit", 3600).set("goal_position", 300).set("run_speed", 90);
  position.set("present_position", 120);
  // Into wheel mode it would turn at 90 at once.
  const auto wheel = position.hold({BusWrite{6, {0, 0, 0, 0}}});
  ASSERT_TRUE(wheel) << wheel.error();
  ASSERT_TRUE(*wheel);
  EXPECT_EQ((*wheel)->writes, (std::vector<BusWrite>{{30, {120, 0, 0, 0, 0, 0}}}));
  EXPECT_NE((*wheel)->what.find("drive change (position mode -> speed mode)"), std::string::npos) << (*wheel)->what;
  // One limit alone that keeps position mode changes no drive.
  const auto narrower = position.hold({position.write("ccw_angle_limit", 1800)});
  ASSERT_TRUE(narrower) << narrower.error();
  EXPECT_FALSE(*narrower);
  // Asleep, a drive change moves nothing: the wake will get the hold.
  position.set("sleep", 1);
  const auto asleep = position.hold({BusWrite{6, {0, 0, 0, 0}}});
  ASSERT_TRUE(asleep) << asleep.error();
  EXPECT_FALSE(*asleep);
}

TEST(EnableFields, TorqueOnHoldsWhereTheTorqueWasOffOrDampingAndNotWhereItIsOn) {
  State off(TableId::Sts);
  off.set("operating_mode", 0).set("torque_enable", 0).set("goal_position", 4000).set("present_position", 10);
  const auto hold = off.hold({off.write("torque_enable", 1)});
  ASSERT_TRUE(hold && *hold);
  EXPECT_EQ((*hold)->writes, (std::vector<BusWrite>{{41, {0, 10, 0, 0, 0, 0, 0}}}));
  // The log line the torque-on tests look for.
  EXPECT_EQ((*hold)->what.rfind("torque on: hold (position mode: goal := present position 10)", 0), 0u)
      << (*hold)->what;

  State damping(TableId::Sts);  // 2: free but braked
  damping.set("operating_mode", 1).set("torque_enable", 2).set("goal_speed", 700);
  const auto speed = damping.hold({damping.write("torque_enable", 1)});
  ASSERT_TRUE(speed && *speed);
  EXPECT_EQ((*speed)->drive, Drive::Velocity);
  EXPECT_EQ((*speed)->writes, (std::vector<BusWrite>{{41, {0, 0, 0, 0, 0, 0, 0}}}));

  State sms1(TableId::Sms1);
  sms1.set("operating_mode", 2).set("torque_switch", 0).set("run_time", 300);
  const auto pwm = sms1.hold({sms1.write("torque_switch", 1)});
  ASSERT_TRUE(pwm && *pwm);
  EXPECT_EQ((*pwm)->drive, Drive::Pwm);

  State on(TableId::Smsmb);
  on.set("mode", 0).set("torque_switch", 1);
  const auto again = on.hold({on.write("torque_switch", 1)});
  ASSERT_TRUE(again);
  EXPECT_FALSE(*again) << "a hold would cancel the move under way";
  const auto calibrate = off.hold({off.write("torque_enable", 128)});
  ASSERT_TRUE(calibrate);
  EXPECT_FALSE(*calibrate);
}

TEST(EnableFields, AModeChangeOfAnEnabledServoNeutralisesTheWholeGoalBlock) {
  State sts(TableId::Sts);
  sts.set("operating_mode", 0).set("torque_enable", 1).set("goal_position", 4000).set("goal_time", 300);
  sts.set("goal_speed", 1500).set("present_position", 2000);
  const auto speed = sts.hold({sts.write("operating_mode", 1)});
  ASSERT_TRUE(speed) << speed.error();
  ASSERT_TRUE(*speed);
  // 42-47: goal 2000 (0x07D0), time 0, speed 0.
  EXPECT_EQ((*speed)->writes, (std::vector<BusWrite>{{41, {0, 0xD0, 0x07, 0, 0, 0, 0}}}));
  EXPECT_NE((*speed)->what.find("drive change (position mode -> speed mode)"), std::string::npos);
  // Into step mode the same; a mode value of the same drive is no change.
  const auto step = sts.hold({sts.write("operating_mode", 3)});
  ASSERT_TRUE(step && *step);
  EXPECT_EQ((*step)->writes, (*speed)->writes);
  const auto same = sts.hold({sts.write("operating_mode", 0)});
  ASSERT_TRUE(same);
  EXPECT_FALSE(*same);
  // With the torque off nothing moves: the torque on will get the hold of the new mode.
  sts.set("torque_enable", 0);
  const auto off = sts.hold({sts.write("operating_mode", 1)});
  ASSERT_TRUE(off);
  EXPECT_FALSE(*off);
  // Mode and torque in one request: the neutral block, written before either.
  const auto both = sts.hold({sts.write("operating_mode", 1), sts.write("torque_enable", 1)});
  ASSERT_TRUE(both && *both);
  EXPECT_EQ((*both)->writes, (std::vector<BusWrite>{{41, {0, 0xD0, 0x07, 0, 0, 0, 0}}}));

  State smsmb(TableId::Smsmb);
  smsmb.set("mode", 1).set("torque_switch", 1).set("goal_position", 3000).set("running_speed", -500);
  smsmb.set("acceleration", 20).set("present_position", -2);
  const auto position = smsmb.hold({smsmb.write("mode", 0)});
  ASSERT_TRUE(position && *position);
  EXPECT_EQ((*position)->writes, (std::vector<BusWrite>{{0x80, {0xFF, 0xFE, 0, 1, 0, 20, 0, 0}}}));

  State scs(TableId::Scs);  // both angle limits 0: PWM; duty in goal_time
  scs.set("min_angle_limit", 0).set("max_angle_limit", 1023).set("torque_enable", 1).set("goal_time", 500);
  scs.set("goal_speed", 300).set("present_position", 512);
  const auto pwm = scs.hold({scs.write("max_angle_limit", 0)});
  ASSERT_TRUE(pwm && *pwm);
  EXPECT_EQ((*pwm)->writes, (std::vector<BusWrite>{{42, {0x02, 0x00, 0, 0, 0, 0}}}));  // high byte first
}

TEST(EnableFields, LeavingStepModeSwitchesTheTorqueOffOrIsRefusedWithAnEnable) {
  State step(TableId::Sts);
  step.set("operating_mode", 3).set("torque_enable", 1).set("goal_position", 500);
  const auto leave = step.hold({step.write("operating_mode", 0)});
  ASSERT_TRUE(leave && *leave);
  EXPECT_EQ((*leave)->writes, (std::vector<BusWrite>{{40, {0}}}));
  step.set("torque_enable", 0);
  const auto refused = step.hold({step.write("operating_mode", 0), step.write("torque_enable", 1)});
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().find("write the mode first"), std::string::npos) << refused.error();
  // Enabled in step mode: no goal is stale there.
  const auto in_step = step.hold({step.write("torque_enable", 1)});
  ASSERT_TRUE(in_step);
  EXPECT_FALSE(*in_step);
}

TEST(EnableFields, AStateNotReadWholeIsAnError) {
  const MotionSpec& d55d = motion_spec(TableId::D55d);
  const std::vector<BusRange> ranges = stop_context_reads(d55d);  // without sleep and brake
  std::vector<Bytes> data;
  for (const auto& range : ranges) data.emplace_back(range.count, 0);
  const std::vector<BusWrite> wake{{47, {0}}};
  EXPECT_FALSE(plan_enable_hold(d55d, ByteOrder::LowFirst, StopContext{ranges, data}, wake));
}

using testing::read_file;

// docs/SAFETY.md's table of enabling writes is the table data's.
TEST(EnableFields, SafetyDocListsEveryTablesEnablingWrites) {
  const std::string safety = read_file(SMS_SAFETY_DOC_PATH);
  ASSERT_FALSE(safety.empty()) << SMS_SAFETY_DOC_PATH;
  for (const TableSpec* t : all_tables()) {
    const std::string row = "| `" + std::string(t->name) + "` | " + enabling_writes_text(t->id) + " |";
    EXPECT_NE(safety.find(row), std::string::npos) << SMS_SAFETY_DOC_PATH << " lacks the row\n" << row;
  }
}

}  // namespace
}  // namespace sms::modbus_map
