// Timed group moves' plan: counts of speed and acceleration whose trapezoid takes the time asked.
#include "modbus_map/timed_move.h"

#include <gtest/gtest.h>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

TEST(TimedMove, TrapezoidAndTriangleTimes) {
  EXPECT_DOUBLE_EQ(move_seconds(1000, 500, 1000), 2.5);  // d/v + v/a
  EXPECT_DOUBLE_EQ(move_seconds(100, 1000, 100), 2.0);   // never reaches v: 2·√(d/a)
  EXPECT_DOUBLE_EQ(move_seconds(300, 100, 0), 3.0);      // no ramps
  EXPECT_DOUBLE_EQ(move_seconds(0, 100, 100), 0.0);
}

TEST(TimedMove, EveryTableNamesWritableFieldsOfItsOwn) {
  for (const TableSpec* table : all_tables()) {
    const TimedMoveSpec* spec = timed_move_spec(table->id);
    ASSERT_NE(spec, nullptr) << table->name;
    for (const std::string_view name : {spec->speed, spec->acceleration, spec->time, spec->deceleration}) {
      if (name.empty()) continue;
      const FieldSpec* field = field_by_name(*table, name);
      ASSERT_NE(field, nullptr) << table->name << " has no " << name;
      EXPECT_NE(field->access, Access::ReadOnly) << table->name << "." << name;
    }
    EXPECT_GT(spec->max_speed, 0);
    if (const FieldSpec* acceleration = field_by_name(*table, spec->acceleration)) {
      EXPECT_LE(spec->max_acceleration, acceleration->max) << table->name;
    }
    EXPECT_LE(spec->max_speed, field_by_name(*table, spec->speed)->max) << table->name;
  }
}

// Distances from 100 to 3000 steps in 1.5 s, each within 1 % on every table.
TEST(TimedMove, PlansLandWithinOnePercentOfTheTimeAsked) {
  for (const TableId id : {TableId::Sts, TableId::Sms1, TableId::Smsmb, TableId::Scs}) {
    const TimedMoveSpec& spec = *timed_move_spec(id);
    // scs: 1024 steps over 300°, so its longest move is shorter.
    const double longest = id == TableId::Scs ? 1000 : 3000;
    for (double distance = 100; distance <= longest; distance += 100) {
      const auto plan = plan_axis(spec, distance, 1.5);
      ASSERT_TRUE(plan.has_value()) << static_cast<int>(id) << " " << distance;
      EXPECT_NEAR(plan->seconds, 1.5, 0.015) << static_cast<int>(id) << " " << distance;
      EXPECT_GE(plan->speed, 1);
      EXPECT_LE(plan->speed, spec.max_speed);
      EXPECT_LE(plan->acceleration, spec.max_acceleration);
      const double a = spec.acceleration.empty() ? 0.0 : plan->acceleration * spec.acceleration_unit;
      EXPECT_DOUBLE_EQ(move_seconds(distance, plan->speed * spec.speed_unit, a), plan->seconds);
    }
  }
}

// d55d positions count degrees × resolution: at the default 10 (1°), 10 °/s² is 10 units/s² and
// 360 °/s is 360 units/s; at 5 (0.5°) twice as many units.
TEST(TimedMove, D55dUnitsFollowTheAngleResolution) {
  const TimedMoveSpec& d55d = *timed_move_spec(TableId::D55d);
  EXPECT_NE(field_by_name(table(TableId::D55d), d55d.resolution), nullptr);
  const TimedMoveSpec same = at_resolution(d55d, 10);
  EXPECT_DOUBLE_EQ(same.acceleration_unit, 10.0);
  EXPECT_EQ(same.max_speed, 360);
  const TimedMoveSpec finer = at_resolution(d55d, 5);
  EXPECT_DOUBLE_EQ(finer.acceleration_unit, 20.0);
  EXPECT_EQ(finer.max_speed, 720);
  EXPECT_DOUBLE_EQ(finer.speed_unit, 1.0);  // run speed counts position units per second
  for (double distance = 10; distance <= 350; distance += 10) {
    const auto plan = plan_axis(same, distance, 1.5);
    ASSERT_TRUE(plan.has_value()) << distance;
    EXPECT_NEAR(plan->seconds, 1.5, 0.015) << distance;
  }
  // A table without a resolution field keeps its units.
  EXPECT_DOUBLE_EQ(at_resolution(*timed_move_spec(TableId::Sts), 5).acceleration_unit, 100.0);
}

TEST(TimedMove, ATimeShorterThanTheFastestMoveIsRefused) {
  const TimedMoveSpec& sts = *timed_move_spec(TableId::Sts);
  const double fastest = shortest_seconds(sts, 3000);
  EXPECT_GT(fastest, 0.5);
  EXPECT_FALSE(plan_axis(sts, 3000, fastest * 0.99).has_value());
  const auto at_fastest = plan_axis(sts, 3000, fastest);
  ASSERT_TRUE(at_fastest.has_value());
  EXPECT_EQ(at_fastest->speed, sts.max_speed);
}

TEST(TimedMove, NoDistanceNeedsNoTime) {
  const auto plan = plan_axis(*timed_move_spec(TableId::Sts), 0, 0.001);
  ASSERT_TRUE(plan.has_value());
  EXPECT_EQ(plan->seconds, 0);
}

}  // namespace
}  // namespace sms::modbus_map
