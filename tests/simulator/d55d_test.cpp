// `D5 5D` servos through a real pty: every instruction of docs/PROTOCOL.md §1.2 and the motor rules of
// doc 002 (speed 0 stops, heartbeat, photo-switch homing, custom moves, trajectories).
#include <gtest/gtest.h>

#include "protocol/d55d.h"
#include "tests/simulator/sim_fixture.h"

namespace sms::simulator::testing {
namespace {

using protocol::kD55dFormat;
namespace d55d_error = protocol::d55d::error_bit;
namespace d55d_codec = protocol::d55d;

class D55dSim : public ::testing::Test {
 protected:
  void start(std::vector<ServoConfig> servos) { rig = std::make_unique<Rig>(quick_options(std::move(servos))); }
  HostPort& host() { return *rig->host; }

  std::optional<protocol::Packet> ask(const protocol::Packet& request) { return host().transact(kD55dFormat, request); }
  Bytes read(std::uint8_t id, std::uint8_t address, std::uint8_t count) {
    const auto reply = ask(protocol::read(id, address, count));
    return reply ? reply->params : Bytes{};
  }
  void write(std::uint8_t id, std::uint8_t address, Bytes data) {
    ASSERT_EQ(ask(protocol::write(id, address, data)), status(id, 0)) << "WRITE " << int(address);
  }
  // Polling keeps the heartbeat fed, as a host's poll loop does.
  bool reaches(std::uint8_t id, std::uint8_t address, Bytes expected) {
    return eventually([&] { return read(id, address, static_cast<std::uint8_t>(expected.size())) == expected; });
  }
  void wheel_mode(std::uint8_t id) { write(id, 6, {0, 0, 0, 0}); }
  // The frames that came back to `request` before the answer to a PING of servo 1 sent right
  // after it (a PING is answered at every response level). Replies keep their order on the
  // line, so an empty list means `request` went unanswered however slow the machine is: no
  // window of silence is timed.
  std::vector<protocol::Packet> answers_before_ping(const protocol::Packet& request) {
    host().send(protocol::encode(kD55dFormat, request));
    host().send(protocol::encode(kD55dFormat, protocol::ping(1)));
    const protocol::Packet ping_answer = status(1, 0, {0});
    Bytes received;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (std::chrono::steady_clock::now() < deadline) {
      const Bytes more = host().receive(std::chrono::milliseconds(30), std::chrono::milliseconds(200));
      received.insert(received.end(), more.begin(), more.end());
      auto frames = decode_all(kD55dFormat, received);
      if (!frames.empty() && frames.back() == ping_answer) {
        frames.pop_back();
        return frames;
      }
    }
    ADD_FAILURE() << "the PING after the request was not answered: " << hex(received);
    return decode_all(kD55dFormat, received);
  }

  std::unique_ptr<Rig> rig;
};

TEST_F(D55dSim, PingIsAnsweredWithOneParameter) {
  start({d55d(1)});
  host().send({0xD5, 0x5D, 0x01, 0x02, 0x01, 0x04});
  EXPECT_EQ(host().receive_exactly(7), (Bytes{0xD5, 0x5D, 0x01, 0x03, 0x00, 0x00, 0x04}));
}

TEST_F(D55dSim, PingIsAnsweredEvenBroadcastAndAtResponseLevelZero) {
  start({d55d(1)});
  EXPECT_TRUE(answers_before_ping(protocol::write(1, 16, Bytes{0})).empty());
  EXPECT_EQ(ask(protocol::ping(protocol::kBroadcastId)), status(1, 0, {0}));
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0, {0}));
  EXPECT_FALSE(host().transact(kD55dFormat, protocol::read(1, 3, 1), std::chrono::milliseconds(30)))
      << "level 0: nothing but PING is answered";
}

TEST_F(D55dSim, ResponseLevelOneAnswersReadsOnly) {
  start({d55d(1)});
  // The new level already governs the reply to the WRITE that sets it.
  EXPECT_TRUE(answers_before_ping(protocol::write(1, 16, Bytes{1})).empty());
  EXPECT_TRUE(answers_before_ping(protocol::write(1, 34, Bytes{50})).empty());
  EXPECT_EQ(read(1, 34, 1), Bytes{50});
}

TEST_F(D55dSim, WorkedBroadcastFrameSetsTheIdSilently) {
  start({d55d(7)});
  host().send({0xD5, 0x5D, 0xFE, 0x04, 0x03, 0x03, 0x01, 0x09});
  EXPECT_TRUE(host().receive(std::chrono::milliseconds(30), std::chrono::milliseconds(60)).empty());
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0, {0}));
}

TEST_F(D55dSim, ChecksumErrorIsFlaggedInTheNextReply) {
  start({d55d(1)});
  host().send({0xD5, 0x5D, 0x01, 0x02, 0x01, 0x05});  // PING with a wrong checksum
  EXPECT_TRUE(host().receive(std::chrono::milliseconds(30), std::chrono::milliseconds(60)).empty());
  EXPECT_EQ(ask(protocol::ping(1)), status(1, d55d_error::kChecksum, {0}));
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0, {0})) << "cleared by the next good instruction";
}

TEST_F(D55dSim, UnknownInstructionIsFlagged) {
  start({d55d(1)});
  host().send({0xD5, 0x5D, 0x01, 0x02, 0x09, 0x0C});
  EXPECT_EQ(host().receive_exactly(6), (Bytes{0xD5, 0x5D, 0x01, 0x02, 0x20, 0x23}));
}

TEST_F(D55dSim, WriteToReadOnlyFieldIsRefusedAndNothingWritten) {
  start({d55d(1)});
  EXPECT_EQ(ask(protocol::write(1, 46, Bytes{99})), status(1, d55d_error::kInstruction));
  EXPECT_NE(read(1, 46, 1), Bytes{99});
}

TEST_F(D55dSim, RegWriteSetsTheFlagUntilAction) {
  start({d55d(1)});
  EXPECT_EQ(ask(protocol::reg_write(1, 34, Bytes{12})), status(1, 0));
  EXPECT_EQ(read(1, 44, 1), Bytes{1});
  EXPECT_EQ(read(1, 34, 1), Bytes{36});
  EXPECT_EQ(ask(protocol::action(1)), status(1, 0));
  EXPECT_EQ(read(1, 44, 1), Bytes{0});
  EXPECT_EQ(read(1, 34, 1), Bytes{12});
}

TEST_F(D55dSim, ActionWithoutRegWriteIsFlagged) {
  start({d55d(1)});
  EXPECT_EQ(ask(protocol::action(1)), status(1, d55d_error::kInstruction));
}

TEST_F(D55dSim, SyncWriteSetsEachListedServo) {
  start({d55d(1), d55d(2)});
  const std::vector<protocol::SyncWriteEntry> entries{{1, {20}}, {2, {30}}};
  EXPECT_TRUE(answers_before_ping(protocol::sync_write(34, 1, entries)).empty());
  EXPECT_EQ(read(1, 34, 1), Bytes{20});
  EXPECT_EQ(read(2, 34, 1), Bytes{30});
}

TEST_F(D55dSim, ResetRestoresFactoryValuesIncludingTheBaud) {
  start({d55d(1)});
  write(1, 11, {60});  // max temperature
  EXPECT_EQ(ask(d55d_codec::reset(1)), status(1, 0));
  EXPECT_FALSE(host().transact(kD55dFormat, protocol::ping(1), std::chrono::milliseconds(30)))
      << "factory baud code 0 is 9600 on a finger/wrist motor";
  host().set_baud(9'600);
  EXPECT_EQ(read(1, 11, 1), Bytes{80});
}

TEST_F(D55dSim, MovesToTheGoalAtTheRunSpeed) {
  start({d55d(1)});
  write(1, 34, {200, 200});    // acceleration, deceleration 2000 °/s²
  write(1, 32, {0x68, 0x01});  // 360 °/s
  write(1, 30, {0x5A, 0x00});  // 90°
  EXPECT_EQ(read(1, 42, 1), Bytes{1});
  EXPECT_TRUE(reaches(1, 36, {0x5A, 0x00}));
  EXPECT_TRUE(reaches(1, 42, {0})) << "the deceleration tail ends";
}

TEST_F(D55dSim, GoalIsClampedToTheAngleLimits) {
  start({d55d(1)});
  write(1, 6, {0x0A, 0x00, 0x1E, 0x00});  // CW 10, CCW 30
  write(1, 32, {0x68, 0x01});
  write(1, 30, {0x64, 0x00});  // 100 -> 30
  EXPECT_EQ(read(1, 30, 2), (Bytes{0x1E, 0x00}));
  EXPECT_TRUE(reaches(1, 36, {0x1E, 0x00}));
}

TEST_F(D55dSim, WheelModeTurnsAtTheSignedSpeedAndZeroStops) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x64, 0x80});  // 100 °/s clockwise (bit 15)
  EXPECT_TRUE(reaches(1, 38, {0x9C, 0xFF})) << "present speed -100, two's complement";
  const Bytes angle = read(1, 40, 2);
  ASSERT_EQ(angle.size(), 2U);
  EXPECT_LT(static_cast<std::int16_t>(angle[0] | angle[1] << 8), 0) << "accumulated angle runs negative";
  write(1, 32, {0x00, 0x00});
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
  EXPECT_EQ(read(1, 38, 2), (Bytes{0x00, 0x00}));
}

TEST_F(D55dSim, HeartbeatStopsTheMotorAfter500msOfSilence) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x64, 0x00});
  std::this_thread::sleep_for(std::chrono::milliseconds(620));
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
}

TEST_F(D55dSim, WithoutHeartbeatTheMotorKeepsTurning) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 17, {0});
  write(1, 32, {0x64, 0x00});
  std::this_thread::sleep_for(std::chrono::milliseconds(620));
  EXPECT_EQ(read(1, 42, 1), Bytes{1});
}

TEST_F(D55dSim, BrakeStopsAtOnceAndHolds) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x64, 0x00});
  write(1, 43, {1});
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
  write(1, 32, {0x64, 0x00});
  EXPECT_EQ(read(1, 42, 1), Bytes{0}) << "braked: speed commands wait for the brake to be released";
}

// What the gateway's "no jump on enable" guards against (doc 002: brake and sleep only pause the
// motor): released or woken, it takes up the speed or the goal it holds.
TEST_F(D55dSim, ReleasingTheBrakeResumesTheTurnAndTheMoveItHolds) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x5A, 0x00});  // 90 °/s
  EXPECT_TRUE(reaches(1, 38, {0x5A, 0x00}));
  write(1, 43, {1});
  EXPECT_EQ(read(1, 38, 2), (Bytes{0x00, 0x00}));
  write(1, 43, {0});
  EXPECT_TRUE(reaches(1, 38, {0x5A, 0x00})) << "released, it turns at the speed it holds";

  write(1, 6, {0x00, 0x00, 0x68, 0x01});  // position mode, 0..360°
  write(1, 32, {0x3C, 0x00});             // 60 °/s
  write(1, 30, {0x00, 0x00});
  EXPECT_TRUE(reaches(1, 42, {0}));
  write(1, 30, {0x2C, 0x01});  // 300°
  EXPECT_TRUE(eventually([&] {
    const Bytes present = read(1, 36, 2);
    return present.size() == 2 && (present[0] | present[1] << 8) >= 20;
  }));
  write(1, 43, {1});
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
  write(1, 43, {0});
  EXPECT_EQ(read(1, 42, 1), Bytes{1}) << "released, it resumes its move";
  EXPECT_TRUE(reaches(1, 36, {0x2C, 0x01}));
}

TEST_F(D55dSim, SleepFreesTheMotorAndWakingResumesTheRunSpeed) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x5A, 0x00});
  EXPECT_TRUE(reaches(1, 38, {0x5A, 0x00}));
  write(1, 47, {1});
  EXPECT_EQ(read(1, 38, 2), (Bytes{0x00, 0x00}));
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
  write(1, 32, {0x5A, 0x00});
  EXPECT_EQ(read(1, 42, 1), Bytes{0}) << "asleep: speed commands wait for the wake";
  write(1, 47, {0});
  EXPECT_TRUE(reaches(1, 38, {0x5A, 0x00})) << "woken, it turns at the speed it holds";
}

TEST_F(D55dSim, PhotoSwitchHomingFindsZeroThenTheEndAndRecordsTheTravel) {
  start({d55d(1)});
  write(1, 19, {1});  // zero on the clockwise side
  write(1, 24, {1});  // start
  const Bytes running = read(1, 24, 1);
  ASSERT_EQ(running.size(), 1U);
  EXPECT_EQ(running[0] >> 4, 1) << "high nibble 1: running";
  ASSERT_TRUE(eventually([&] { return read(1, 24, 1) == Bytes{0x20}; })) << "high nibble 2: done";
  EXPECT_EQ(read(1, 8, 2), (Bytes{0x90, 0x01})) << "CCW limit = the 400° travel";
  EXPECT_EQ(read(1, 36, 2), (Bytes{0x90, 0x01})) << "stopped on the end switch";
  EXPECT_EQ(read(1, 48, 1), Bytes{2}) << "switch 2 high";
}

TEST_F(D55dSim, HomingStopsWhenAskedTo) {
  start({d55d(1)});
  write(1, 24, {1});
  write(1, 24, {0});
  EXPECT_EQ(read(1, 24, 1), Bytes{0x00});
  EXPECT_EQ(read(1, 42, 1), Bytes{0});
}

TEST_F(D55dSim, CustomRelativeMoveTurnsByTheAngleInTheSpeedsDirection) {
  start({d55d(1)});
  const d55d_codec::RelativeMove move{30, 0x0168, std::nullopt, std::nullopt};  // +30° at 360 °/s
  EXPECT_EQ(ask(d55d_codec::custom(1, move)), status(1, 0));
  EXPECT_TRUE(reaches(1, 36, {0x1E, 0x00}));
  const d55d_codec::RelativeMove back{10, 0x8168, 100, 100};  // 10° clockwise
  EXPECT_EQ(ask(d55d_codec::custom(1, back)), status(1, 0));
  EXPECT_TRUE(reaches(1, 36, {0x14, 0x00}));
}

TEST_F(D55dSim, CustomAbsoluteMoveSetsAccelerationAndDeceleration) {
  start({d55d(1)});
  const d55d_codec::AbsoluteMove move{45, 0x0168, 90, 80};
  EXPECT_EQ(ask(d55d_codec::custom(1, move)), status(1, 0));
  EXPECT_EQ(read(1, 34, 2), (Bytes{90, 80}));
  EXPECT_TRUE(reaches(1, 36, {0x2D, 0x00}));
}

TEST_F(D55dSim, CustomChangeSpeedKeepsTheDirection) {
  start({d55d(1)});
  wheel_mode(1);
  write(1, 32, {0x64, 0x80});  // 100 clockwise
  EXPECT_EQ(ask(d55d_codec::custom(1, d55d_codec::ChangeSpeed{200})), status(1, 0));
  EXPECT_EQ(read(1, 32, 2), (Bytes{0xC8, 0x80}));
  EXPECT_TRUE(reaches(1, 38, {0x38, 0xFF}));  // -200
}

TEST_F(D55dSim, TrajectoryRunsItsPointsInOrder) {
  start({d55d(1)});
  write(1, 34, {200, 200});
  const std::vector<d55d_codec::TrajectoryPoint> points{{40, 250}, {20, 250}};
  EXPECT_EQ(ask(d55d_codec::trajectory_write(1, points)), status(1, 0));
  EXPECT_EQ(read(1, 42, 1), Bytes{0}) << "stored, not run";
  EXPECT_EQ(ask(d55d_codec::trajectory_action(1)), status(1, 0));
  // The first point is passed through, so look for "near 40" rather than exactly 40.
  EXPECT_TRUE(eventually([&] {
    const Bytes position = read(1, 36, 2);
    return position.size() == 2 && position[0] >= 35;
  }));
  EXPECT_TRUE(reaches(1, 36, {0x14, 0x00}));
  EXPECT_TRUE(reaches(1, 42, {0}));
}

TEST_F(D55dSim, TrajectoryActionWithoutPointsIsFlagged) {
  start({d55d(1)});
  EXPECT_EQ(ask(d55d_codec::trajectory_action(1)), status(1, d55d_error::kInstruction));
}

TEST_F(D55dSim, StartEndSetsTheAngleLimits) {
  start({d55d(1)});
  const Bytes params{0x05, 0x00, 0x2C, 0x01};  // 5 .. 300
  EXPECT_EQ(ask(d55d_codec::start_end(1, params)), status(1, 0));
  EXPECT_EQ(read(1, 6, 4), params);
}

TEST_F(D55dSim, InjectedOverTemperatureIsReported) {
  start({d55d(1)});
  rig->bus->set_error_bits(1, d55d_error::kOverTemperature);
  EXPECT_EQ(ask(protocol::ping(1)), status(1, d55d_error::kOverTemperature, {0}));
  const Bytes temperature = read(1, 46, 1);
  ASSERT_EQ(temperature.size(), 1U);
  EXPECT_GT(temperature[0], 80);
  EXPECT_EQ(temperature[0] & 0x80, 0) << "positive: sign bit 7 clear";
}

}  // namespace
}  // namespace sms::simulator::testing
