#include "simulator/motion_model.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace sms::simulator {
namespace {

constexpr double kMaxStep = 0.001;  // s: fine enough for a 1 kHz servo loop

// Moves `from` toward `to` by at most `rate * dt`; rate 0 means at once.
double approach(double from, double to, double rate, double dt) {
  if (rate <= 0) return to;
  const double max_change = rate * dt;
  if (std::abs(to - from) <= max_change) return to;
  return from + std::copysign(max_change, to - from);
}

// Slowing down (toward zero, same sign) uses the deceleration, anything else the acceleration.
double ramp_rate(double from, double to, const MotionLimits& limits) {
  const bool slowing = std::abs(to) < std::abs(from) && (to == 0 || (to > 0) == (from > 0));
  return slowing ? limits.deceleration : limits.acceleration;
}

}  // namespace

void MotionModel::commanded() {
  direction_ = velocity_ > 0 ? 1 : (velocity_ < 0 ? -1 : 0);
  reversed_ = false;
  commanded_direction_ = direction_;
  farthest_ = position_;
}

double MotionModel::turned_back() const {
  return commanded_direction_ == 0 ? 0.0 : std::max(0.0, (farthest_ - position_) * commanded_direction_);
}

void MotionModel::note_direction() {
  if (commanded_direction_ != 0 && (position_ - farthest_) * commanded_direction_ > 0) farthest_ = position_;
  const int now = velocity_ > 0 ? 1 : (velocity_ < 0 ? -1 : 0);
  if (now == 0) return;
  if (direction_ != 0 && now != direction_) reversed_ = true;
  direction_ = now;
}

void MotionModel::release() {
  commanded();
  drive_ = Drive::Free;
  velocity_ = 0;
  acceleration_ = 0;
  target_ = position_;
}

void MotionModel::hold() {
  commanded();
  drive_ = Drive::Hold;
  velocity_ = 0;
  acceleration_ = 0;
  target_ = position_;
}

void MotionModel::move_to(double target, const MotionLimits& limits) {
  commanded();
  drive_ = Drive::Position;
  target_ = target;
  limits_ = limits;
}

void MotionModel::run_at(double velocity, const MotionLimits& limits) {
  commanded();
  drive_ = Drive::Velocity;
  commanded_velocity_ = std::clamp(velocity, -limits.max_speed, limits.max_speed);
  limits_ = limits;
}

void MotionModel::shift(double delta) {
  position_ += delta;
  target_ += delta;
}

bool MotionModel::steady() const {
  switch (drive_) {
    case Drive::Free:
    case Drive::Hold: return true;
    case Drive::Position: return arrived();
    case Drive::Velocity: return velocity_ == commanded_velocity_;
  }
  return true;
}

std::optional<double> MotionModel::advance(double seconds) {
  std::optional<double> arrival;
  double elapsed = 0;
  while (seconds > 0) {
    if (steady()) {
      position_ += velocity_ * seconds;
      acceleration_ = 0;
      note_direction();
      return arrival;
    }
    const double dt = std::min(seconds, kMaxStep);
    step(dt);
    seconds -= dt;
    elapsed += dt;
    if (arrived()) arrival = elapsed;
  }
  return arrival;
}

void MotionModel::step(double dt) {
  const double before = velocity_;
  if (drive_ == Drive::Velocity) {
    velocity_ = approach(velocity_, commanded_velocity_, ramp_rate(velocity_, commanded_velocity_, limits_), dt);
    position_ += velocity_ * dt;
  } else if (drive_ == Drive::Position) {
    const double distance = target_ - position_;
    // The fastest speed from which the deceleration, taken in steps of dt, still stops at the
    // target: braking from v covers v²/2a + v·dt/2 in steps (the continuous √(2·a·d) would arrive
    // some 20 ms early, and a timed move would miss its time by that).
    const double a = limits_.deceleration;
    const double stopping_speed = a > 0 ? (std::sqrt(a * a * dt * dt + 8 * a * std::abs(distance)) - a * dt) / 2
                                        : std::numeric_limits<double>::infinity();
    const double wanted = std::copysign(std::min(limits_.max_speed, stopping_speed), distance);
    velocity_ = approach(velocity_, wanted, ramp_rate(velocity_, wanted, limits_), dt);
    const double next = position_ + velocity_ * dt;
    if (distance == 0 || (target_ - next) * distance <= 0) {
      position_ = target_;  // would pass it: arrived
      velocity_ = 0;
    } else {
      position_ = next;
    }
  }
  acceleration_ = (velocity_ - before) / dt;
  note_direction();
}

}  // namespace sms::simulator
