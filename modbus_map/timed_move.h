#pragma once
// Timed group moves (docs/PLC_GUIDE.md "Timed moves"): what a table needs so the gateway can
// make an axis take a given time for a given distance, and the plan itself. The profile is the
// servos' own trapezoid: ramp up at a, run at v, brake at a, so a move of d takes
// T = d/v + v/a (2·√(d/a) when it never reaches v). Speeds and accelerations are whole field
// counts, so the plan searches the counts for the time nearest T. Data and arithmetic, no I/O.
#include <cstdint>
#include <optional>
#include <string_view>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

struct TimedMoveSpec {
  TableId table;
  std::string_view speed;         // the goal speed field written with the goal
  std::string_view acceleration;  // empty: the table has none (the servo changes speed at once)
  // A move-time field between the goal and the speed, written 0 so the speed governs (the
  // vendors' WritePosEx writes acceleration, goal, 0 and speed as one block); empty: none.
  std::string_view time;
  double speed_unit;         // position units/s per count of `speed`
  double acceleration_unit;  // position units/s² per count of `acceleration`
  // The largest counts a plan uses: the motor's rated no-load speed (the field allows more than
  // the motor runs) and the acceleration field's largest value.
  std::int32_t max_speed;
  std::int32_t max_acceleration;
  std::string_view deceleration;  // written with the acceleration's count; empty: none
  // d55d: positions count degrees × this field (0.1° a count), so `acceleration_unit` and
  // `max_speed` hold at `reference_resolution` and scale with the servo's own (at_resolution);
  // empty: the units are fixed.
  std::string_view resolution;
  std::int32_t reference_resolution;
};

// nullptr: the table cannot take a timed move.
const TimedMoveSpec* timed_move_spec(TableId table);
// `spec` for a servo whose resolution field reads `resolution` (>= 1); `spec` itself when its
// table has no such field.
TimedMoveSpec at_resolution(const TimedMoveSpec& spec, std::int32_t resolution);

// Seconds a move of `distance` (position units, >= 0) takes at top speed `speed` (units/s, > 0)
// ramping at `acceleration` (units/s²; 0: at once).
double move_seconds(double distance, double speed, double acceleration);

struct AxisPlan {
  std::int32_t speed = 0;         // counts of the speed field
  std::int32_t acceleration = 0;  // counts of the acceleration field (0 without one)
  double seconds = 0;             // what the move takes with these counts
};

// The fastest the axis makes `distance`: the largest speed and acceleration.
double shortest_seconds(const TimedMoveSpec& spec, double distance);
// The slowest: one count of speed and of acceleration (a longer time cannot be planned).
double longest_seconds(const TimedMoveSpec& spec, double distance);
// The counts whose move time is nearest `seconds`; nullopt when the axis cannot make it
// (shortest_seconds > seconds). A distance of 0 gets the largest counts (nothing moves).
std::optional<AxisPlan> plan_axis(const TimedMoveSpec& spec, double distance, double seconds);

}  // namespace sms::modbus_map
