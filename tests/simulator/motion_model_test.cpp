// The motor model on its own: profiles, limits, no clock.
#include "simulator/motion_model.h"

#include <gtest/gtest.h>

namespace sms::simulator {
namespace {

TEST(MotionModel, ReachesTheTargetAtTopSpeedWithoutAcceleration) {
  MotionModel motor(0);
  motor.move_to(100, MotionLimits{1000, 0, 0});
  motor.advance(0.05);
  EXPECT_NEAR(motor.position(), 50, 1e-9);
  EXPECT_DOUBLE_EQ(motor.velocity(), 1000);
  motor.advance(0.1);
  EXPECT_TRUE(motor.arrived());
  EXPECT_DOUBLE_EQ(motor.position(), 100);
  EXPECT_DOUBLE_EQ(motor.velocity(), 0);
}

// A trapezoid's time is d/v + v/a (accelerating and braking at a): 1000 steps at 500 steps/s
// with 1000 steps/s² take 2 + 0.5 s. The arrival is told to the millisecond inside one advance.
TEST(MotionModel, TellsWhenInsideAnAdvanceItArrived) {
  MotionModel motor(0);
  motor.move_to(1000, MotionLimits{500, 1000, 1000});
  const auto arrival = motor.advance(4.0);
  ASSERT_TRUE(arrival.has_value());
  EXPECT_NEAR(*arrival, 2.5, 0.002);
  EXPECT_FALSE(motor.advance(1.0).has_value());  // already there: no new arrival
}

TEST(MotionModel, AccelerationRampsTheSpeedUp) {
  MotionModel motor(0);
  motor.move_to(10'000, MotionLimits{1000, 2000, 2000});
  motor.advance(0.25);
  EXPECT_NEAR(motor.velocity(), 500, 2);
  EXPECT_NEAR(motor.position(), 62.5, 2);
  motor.advance(1.0);
  EXPECT_DOUBLE_EQ(motor.velocity(), 1000);
}

TEST(MotionModel, DecelerationStopsOnTheTargetWithoutOvershoot) {
  MotionModel motor(0);
  motor.move_to(1000, MotionLimits{1000, 4000, 4000});
  double furthest = 0;
  for (int step = 0; step < 2000 && !motor.arrived(); ++step) {
    motor.advance(0.001);
    furthest = std::max(furthest, motor.position());
  }
  EXPECT_TRUE(motor.arrived());
  EXPECT_LE(furthest, 1000);
}

TEST(MotionModel, VelocityModeKeepsTurningAndIntegratesLongGaps) {
  MotionModel motor(0);
  motor.run_at(-300, MotionLimits{1000, 0, 0});
  motor.advance(10.0);
  EXPECT_DOUBLE_EQ(motor.position(), -3000);
  EXPECT_TRUE(motor.steady());
}

TEST(MotionModel, CommandedVelocityIsCappedAtTheTopSpeed) {
  MotionModel motor(0);
  motor.run_at(5000, MotionLimits{1000, 0, 0});
  motor.advance(0.01);
  EXPECT_DOUBLE_EQ(motor.velocity(), 1000);
}

TEST(MotionModel, ReleaseAndHoldStopAtOnce) {
  MotionModel motor(0);
  motor.run_at(500, MotionLimits{1000, 0, 0});
  motor.advance(0.1);
  motor.hold();
  EXPECT_DOUBLE_EQ(motor.velocity(), 0);
  const double where = motor.position();
  motor.advance(1.0);
  EXPECT_DOUBLE_EQ(motor.position(), where);
  motor.release();
  EXPECT_EQ(motor.drive(), MotionModel::Drive::Free);
}

TEST(MotionModel, ShiftRebasesWithoutMoving) {
  MotionModel motor(100);
  motor.move_to(200, MotionLimits{1000, 0, 0});
  motor.shift(-100);
  EXPECT_DOUBLE_EQ(motor.position(), 0);
  EXPECT_DOUBLE_EQ(motor.target(), 100);
}

}  // namespace
}  // namespace sms::simulator
