#pragma once
// The motor and its load, in the table's position units: a trapezoidal speed profile toward
// a goal position (acceleration, deceleration, top speed) or toward a commanded velocity.
// Plain numbers, no clock: the owner steps it with the time that has passed.
#include <cstdint>
#include <optional>

namespace sms::simulator {

struct MotionLimits {
  double max_speed = 0;     // units/s, > 0
  double acceleration = 0;  // units/s²; 0 = instantaneous
  double deceleration = 0;  // units/s²; 0 = instantaneous
};

class MotionModel {
 public:
  enum class Drive : std::uint8_t {
    Free,      // torque off: the motor stops and stays where it is
    Hold,      // torque on, holding the present position
    Position,  // toward target()
    Velocity,  // at commanded_velocity()
  };

  explicit MotionModel(double position = 0) : position_(position), target_(position) {}

  void release();  // torque off
  void hold();     // stop at once and hold here (brake, heartbeat stop)
  void move_to(double target, const MotionLimits& limits);
  void run_at(double velocity, const MotionLimits& limits);
  // Re-bases the coordinate (calibration, zero marking): the motor does not move.
  void shift(double delta);

  // Advances by `seconds`; steps larger than a millisecond are split so the profile holds.
  // Returns how far into `seconds` the motor arrived at its target, when it did in this call.
  std::optional<double> advance(double seconds);
  // Nothing but the position at constant velocity changes with time from here on.
  bool steady() const;
  bool arrived() const { return drive_ == Drive::Position && position_ == target_ && velocity_ == 0; }

  Drive drive() const { return drive_; }
  double position() const { return position_; }
  double velocity() const { return velocity_; }
  double acceleration() const { return acceleration_; }  // of the last step
  double target() const { return target_; }
  double commanded_velocity() const { return commanded_velocity_; }
  const MotionLimits& limits() const { return limits_; }
  // Whether the motor turned back since its last command (move_to, run_at, hold, release): the
  // witness of a stop that drives an axis back to a goal it ran past.
  bool reversed() const { return reversed_; }
  // How far it came back from the farthest point it reached, in the direction it had at its
  // last command: 0 for a stop that stands where it braked to.
  double turned_back() const;

 private:
  void step(double dt);
  void commanded();       // a new command: the direction from here is the one it had
  void note_direction();  // after the velocity changed

  Drive drive_ = Drive::Hold;
  double position_;
  double target_;
  double velocity_ = 0;
  double acceleration_ = 0;
  double commanded_velocity_ = 0;
  MotionLimits limits_{1, 0, 0};
  int direction_ = 0;  // -1, 0 (not yet moved since the command), 1
  bool reversed_ = false;
  int commanded_direction_ = 0;  // the direction at the last command
  double farthest_ = 0;          // the farthest position reached that way since
};

}  // namespace sms::simulator
