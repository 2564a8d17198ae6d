#include "modbus_map/timed_move.h"

#include <algorithm>
#include <array>
#include <cmath>

namespace sms::modbus_map {
namespace {

// 4096 steps a turn on every table that takes timed moves except scs (1024 over 300°).
constexpr double kStepsPerDegree = 4096.0 / 360.0;
// Feetech's speed unit 0.732 rpm (sts with phase bit 2 clear, as shipped; smsmb) in steps/s.
constexpr double k0732RpmInSteps = 0.732 * 4096.0 / 60.0;
// The SM40BL's 65 rpm at 12 V (doc 001 §15), the rated no-load speed of the 4096-step servos.
constexpr double kFeetechTopSteps = 65.0 * 4096.0 / 60.0;
constexpr double kScsTopSteps = 1500.0;  // the SCSCL SDK examples' "maximum speed"

constexpr std::int32_t kFeetechTopCounts = static_cast<std::int32_t>(kFeetechTopSteps / k0732RpmInSteps);
constexpr double kSms1SpeedUnit = 0.087 * kStepsPerDegree;

constexpr std::array kSpecs{
    TimedMoveSpec{TableId::Sts, "goal_speed", "acceleration", "goal_time", k0732RpmInSteps, 100.0, kFeetechTopCounts,
                  254, "", "", 0},
    TimedMoveSpec{TableId::Sms1, "run_speed", "acceleration", "run_time", kSms1SpeedUnit, 100.0,
                  static_cast<std::int32_t>(kFeetechTopSteps / kSms1SpeedUnit), 254, "", "", 0},
    // SMSMB's acceleration unit 8.79 °/s² is 100 steps/s²; its range allows more than the motor
    // does, so the plan stops where the packet tables' byte does.
    TimedMoveSpec{TableId::Smsmb, "running_speed", "acceleration", "", k0732RpmInSteps, 8.79 * kStepsPerDegree,
                  kFeetechTopCounts, 254, "", "", 0},
    TimedMoveSpec{TableId::Scs, "goal_speed", "", "goal_time", 1.0, 0.0, static_cast<std::int32_t>(kScsTopSteps), 0, "",
                  "", 0},
    // d55d (doc 002): run speed in position units/s, acceleration and deceleration 10 °/s², a
    // 360 °/s motor; at the default resolution 10 (1° a position unit) 10 units/s² and 360 units/s.
    TimedMoveSpec{TableId::D55d, "run_speed", "acceleration", "", 1.0, 10.0, 360, 254, "deceleration",
                  "angle_resolution", 10},
};

}  // namespace

const TimedMoveSpec* timed_move_spec(TableId table) {
  for (const TimedMoveSpec& spec : kSpecs) {
    if (spec.table == table) return &spec;
  }
  return nullptr;
}

TimedMoveSpec at_resolution(const TimedMoveSpec& spec, std::int32_t resolution) {
  if (spec.resolution.empty() || resolution < 1) return spec;
  // A finer resolution makes more position units to the degree: the same degrees per second
  // squared are more units, the same top speed more units per second.
  const double scale = static_cast<double>(spec.reference_resolution) / resolution;
  TimedMoveSpec scaled = spec;
  scaled.acceleration_unit = spec.acceleration_unit * scale;
  scaled.max_speed = std::max<std::int32_t>(1, static_cast<std::int32_t>(spec.max_speed * scale));
  return scaled;
}

double move_seconds(double distance, double speed, double acceleration) {
  if (distance <= 0) return 0;
  if (acceleration <= 0) return distance / speed;
  if (speed * speed / acceleration <= distance) return distance / speed + speed / acceleration;
  return 2.0 * std::sqrt(distance / acceleration);  // a triangle: it brakes before reaching the speed
}

double shortest_seconds(const TimedMoveSpec& spec, double distance) {
  return move_seconds(distance, spec.max_speed * spec.speed_unit, spec.max_acceleration * spec.acceleration_unit);
}

double longest_seconds(const TimedMoveSpec& spec, double distance) {
  const bool ramps = !spec.acceleration.empty() && spec.acceleration_unit > 0;
  return move_seconds(distance, spec.speed_unit, ramps ? spec.acceleration_unit : 0.0);
}

std::optional<AxisPlan> plan_axis(const TimedMoveSpec& spec, double distance, double seconds) {
  if (distance <= 0) return AxisPlan{spec.max_speed, spec.max_acceleration, 0};
  if (shortest_seconds(spec, distance) > seconds) return std::nullopt;
  const bool ramps = !spec.acceleration.empty() && spec.acceleration_unit > 0;
  std::optional<AxisPlan> best;
  const auto consider = [&](std::int32_t speed, std::int32_t acceleration) {
    const double time =
        move_seconds(distance, speed * spec.speed_unit, ramps ? acceleration * spec.acceleration_unit : 0.0);
    if (!best || std::abs(time - seconds) < std::abs(best->seconds - seconds)) {
      best = AxisPlan{speed, acceleration, time};
    }
  };
  for (std::int32_t speed = 1; speed <= spec.max_speed; ++speed) {
    const double v = speed * spec.speed_unit;
    if (!ramps) {
      consider(speed, 0);
      continue;
    }
    // T = d/v + v/a gives the acceleration for this speed; the counts either side of it.
    const double run = v * seconds - distance;
    if (run <= 0) continue;  // too slow even without ramps
    const double ideal = v * v / run / spec.acceleration_unit;
    const auto below = static_cast<std::int32_t>(std::floor(ideal));
    for (const std::int32_t count : {below, below + 1}) {
      consider(speed, std::clamp(count, std::int32_t{1}, spec.max_acceleration));
    }
  }
  return best;
}

}  // namespace sms::modbus_map
