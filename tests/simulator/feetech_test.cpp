// Feetech `FF FF` servos (sts, sms1) through a real pty: every instruction of docs/PROTOCOL.md §1.1.
#include <gtest/gtest.h>

#include "protocol/feetech.h"
#include "tests/simulator/sim_fixture.h"

namespace sms::simulator::testing {
namespace {

using protocol::kFeetechFormat;
namespace feetech = protocol::feetech;

class FeetechSim : public ::testing::Test {
 protected:
  void start(std::vector<ServoConfig> servos) { rig = std::make_unique<Rig>(quick_options(std::move(servos))); }
  HostPort& host() { return *rig->host; }

  std::optional<protocol::Packet> ask(const protocol::Packet& request) {
    return host().transact(kFeetechFormat, request);
  }
  Bytes read(std::uint8_t id, std::uint8_t address, std::uint8_t count) {
    const auto reply = ask(protocol::read(id, address, count));
    return reply ? reply->params : Bytes{};
  }
  void write(std::uint8_t id, std::uint8_t address, Bytes data) {
    ASSERT_EQ(ask(protocol::write(id, address, data)), status(id, 0)) << "WRITE " << int(address);
  }
  // Keeps reading until `address` holds `expected` (the motion model moves in real time).
  bool reaches(std::uint8_t id, std::uint8_t address, Bytes expected) {
    return eventually([&] { return read(id, address, static_cast<std::uint8_t>(expected.size())) == expected; });
  }

  std::unique_ptr<Rig> rig;
};

TEST_F(FeetechSim, PingAnswersWithTheWorkedFrame) {
  start({sts(1)});
  host().send({0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB});
  EXPECT_EQ(host().receive_exactly(6), (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC}));
}

TEST_F(FeetechSim, ReadsPresentPosition2048AfterPowerOn) {
  start({sts(1)});
  host().send({0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE});
  EXPECT_EQ(host().receive_exactly(8), (Bytes{0xFF, 0xFF, 0x01, 0x04, 0x00, 0x00, 0x08, 0xF2}));
}

TEST_F(FeetechSim, ReadsTheConfiguredIdentityFields) {
  start({sts(7, 115'200)});
  rig->host->set_baud(115'200);
  // ID 7, baud code 4 (115200), return delay 0 (Feetech's factory value; acts as 50), response
  // level 1 (docs/PROTOCOL.md §2.1, §3, docs/DECISIONS.md "Vendor fidelity").
  EXPECT_EQ(read(7, 5, 4), (Bytes{7, 4, 0, 1}));
}

TEST_F(FeetechSim, ReadOutsideTheTableAnswersWithoutData) {
  start({sts(1)});
  // Feetech firmware has no error bit for a bad request (status bit 4 is unused): the answer
  // carries the status bits only, and no data.
  EXPECT_EQ(ask(protocol::read(1, 200, 10)), status(1, 0));
}

TEST_F(FeetechSim, WorkedWriteFrameMovesTheServoToItsGoal) {
  start({sts(1)});
  write(1, 42, {0xC4, 0x09, 0x00, 0x00, 0xE8, 0x03});  // goal 2500, time 0, speed 1000
  EXPECT_EQ(read(1, 66, 1), Bytes{1}) << "moving right after the goal was written";
  EXPECT_NE(read(1, 58, 2), (Bytes{0x00, 0x00})) << "present speed while moving";
  ASSERT_TRUE(reaches(1, 56, {0xC4, 0x09}));
  EXPECT_EQ(read(1, 66, 1), Bytes{0});
  EXPECT_EQ(read(1, 58, 2), (Bytes{0x00, 0x00}));
  // The worked frame of docs/PROTOCOL.md §1.1: goal 2048 at speed 1000, answered FF FF 01 02 00 FC.
  host().send({0xFF, 0xFF, 0x01, 0x09, 0x03, 0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03, 0xD5});
  EXPECT_EQ(host().receive_exactly(6), (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC}));
  EXPECT_TRUE(reaches(1, 56, {0x00, 0x08}));
}

TEST_F(FeetechSim, GoalSpeedLimitsHowFastItMoves) {
  start({sts(1)});
  write(1, 46, {0x04, 0x00});  // 4 × 0.732 rpm (the factory unit) ≈ 200 steps/s
  write(1, 42, {0x00, 0x09});  // 2304: 256 steps away, ~1.3 s
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const Bytes speed = read(1, 58, 2);
  EXPECT_EQ(speed, (Bytes{0x04, 0x00})) << "present speed = goal speed once cruising";
  const Bytes position = read(1, 56, 2);
  const int present = position.size() == 2 ? position[0] | position[1] << 8 : 0;
  EXPECT_GT(present, 2048 + 40);
  EXPECT_LT(present, 2048 + 120);
}

TEST_F(FeetechSim, WriteToReadOnlyFieldIsIgnoredAndNothingWritten) {
  start({sts(1)});
  // Present position (56) is read-only: the write does not land, and Feetech firmware flags
  // nothing (status bit 4 is unused; docs/DECISIONS.md "Vendor fidelity").
  EXPECT_EQ(ask(protocol::write(1, 56, Bytes{0x00, 0x04})), status(1, 0));
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x00, 0x08}));
}

TEST_F(FeetechSim, ValueOutsideTheFieldRangeIsNotStored) {
  start({sts(1)});
  // Response level is 0 or 1; the field keeps its value, no error bit.
  EXPECT_EQ(ask(protocol::write(1, 8, Bytes{7})), status(1, 0));
  EXPECT_EQ(read(1, 8, 1), Bytes{1});
}

TEST_F(FeetechSim, GoalOutsideTheAngleLimitsIsClampedToThem) {
  start({sts(1)});
  write(1, 9, {0xE8, 0x03, 0xB8, 0x0B});  // limits 1000..3000
  write(1, 42, {0xA0, 0x0F});             // goal 4000
  EXPECT_EQ(read(1, 42, 2), (Bytes{0xB8, 0x0B}));
  EXPECT_TRUE(reaches(1, 56, {0xB8, 0x0B}));
  write(1, 42, {0x64, 0x00});  // goal 100
  EXPECT_EQ(read(1, 42, 2), (Bytes{0xE8, 0x03}));
}

TEST_F(FeetechSim, BroadcastWriteExecutesOnEveryServoSilently) {
  start({sts(1), sts(2)});
  const auto replies = host().transact_all(kFeetechFormat, protocol::write(protocol::kBroadcastId, 41, Bytes{20}));
  EXPECT_TRUE(replies.empty());
  EXPECT_EQ(read(1, 41, 1), Bytes{20});
  EXPECT_EQ(read(2, 41, 1), Bytes{20});
}

TEST_F(FeetechSim, BroadcastPingIsAnswered) {
  start({sts(5)});
  EXPECT_EQ(ask(protocol::ping(protocol::kBroadcastId)), status(5, 0));
}

TEST_F(FeetechSim, ResponseLevelZeroAnswersOnlyReadAndPing) {
  start({sts(1)});
  EXPECT_TRUE(host().transact_all(kFeetechFormat, protocol::write(1, 8, Bytes{0})).empty());
  EXPECT_TRUE(host().transact_all(kFeetechFormat, protocol::write(1, 41, Bytes{9})).empty());
  EXPECT_EQ(read(1, 41, 1), Bytes{9}) << "the unanswered WRITE still executed";
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0));
}

TEST_F(FeetechSim, RegWriteIsHeldUntilAction) {
  start({sts(1)});
  EXPECT_EQ(ask(protocol::reg_write(1, 41, Bytes{33})), status(1, 0));
  EXPECT_EQ(read(1, 41, 1), Bytes{0});
  host().send({0xFF, 0xFF, 0xFE, 0x02, 0x05, 0xFA});  // ACTION, broadcast: no answer
  EXPECT_TRUE(host().receive(std::chrono::milliseconds(30), std::chrono::milliseconds(60)).empty());
  EXPECT_EQ(read(1, 41, 1), Bytes{33});
}

TEST_F(FeetechSim, RegWriteOfReadOnlyFieldLandsNothingOnAction) {
  start({sts(1)});
  EXPECT_EQ(ask(protocol::reg_write(1, 62, Bytes{100})), status(1, 0));
  EXPECT_EQ(ask(protocol::action(1)), status(1, 0));
  EXPECT_NE(read(1, 62, 1), Bytes{100});
}

TEST_F(FeetechSim, SyncWriteSetsEachListedServo) {
  start({sts(1), sts(2), sts(3)});
  const std::vector<protocol::SyncWriteEntry> entries{{1, {11}}, {3, {33}}};
  EXPECT_TRUE(host().transact_all(kFeetechFormat, protocol::sync_write(41, 1, entries)).empty());
  EXPECT_EQ(read(1, 41, 1), Bytes{11});
  EXPECT_EQ(read(2, 41, 1), Bytes{0});
  EXPECT_EQ(read(3, 41, 1), Bytes{33});
}

TEST_F(FeetechSim, SyncReadAnswersInListOrder) {
  start({sts(1), sts(2), sts(3)});
  const std::vector<std::uint8_t> ids{3, 1, 2};
  const auto replies = host().transact_expecting(kFeetechFormat, feetech::sync_read(5, 1, ids), 3);
  ASSERT_EQ(replies.size(), 3U);
  EXPECT_EQ(replies[0], status(3, 0, {3}));
  EXPECT_EQ(replies[1], status(1, 0, {1}));
  EXPECT_EQ(replies[2], status(2, 0, {2}));
}

TEST_F(FeetechSim, SyncReadSkipsServosNotListed) {
  start({sts(1), sts(2)});
  const std::vector<std::uint8_t> ids{2};
  EXPECT_EQ(host().transact_expecting(kFeetechFormat, feetech::sync_read(56, 2, ids), 1),
            (std::vector<protocol::Packet>{status(2, 0, {0x00, 0x08})}));
}

TEST_F(FeetechSim, LockedEepromWriteIsLostAtReboot) {
  start({sts(1)});
  write(1, 13, {60});  // max temperature, lock 1 (default)
  EXPECT_EQ(read(1, 13, 1), Bytes{60});
  EXPECT_TRUE(host().transact_all(kFeetechFormat, feetech::reboot(1)).empty());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  EXPECT_EQ(read(1, 13, 1), Bytes{70});
}

TEST_F(FeetechSim, UnlockedEepromWriteSurvivesReboot) {
  start({sts(1)});
  write(1, 55, {0});
  write(1, 13, {60});
  write(1, 55, {1});
  EXPECT_TRUE(host().transact_all(kFeetechFormat, feetech::reboot(1)).empty());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  EXPECT_EQ(read(1, 13, 1), Bytes{60});
  EXPECT_EQ(read(1, 55, 1), Bytes{1}) << "the lock is RAM: back to its default";
}

TEST_F(FeetechSim, RebootIsSilentDeafForAWhileAndRestoresRam) {
  start({sts(1)});
  write(1, 41, {50});
  host().send({0xFF, 0xFF, 0x01, 0x02, 0x08, 0xF4});  // REBOOT id 1
  EXPECT_TRUE(host().receive(std::chrono::milliseconds(20), std::chrono::milliseconds(40)).empty());
  EXPECT_FALSE(host().transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(20)));
  std::this_thread::sleep_for(std::chrono::milliseconds(120));
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0));
  EXPECT_EQ(read(1, 41, 1), Bytes{0});
}

TEST_F(FeetechSim, RecoveryRestoresTheBackupButNotTheId) {
  start({sts(1)});
  write(1, 55, {0});
  write(1, 13, {65});
  EXPECT_EQ(ask(feetech::backup(1)), status(1, 0));
  write(1, 13, {50});
  EXPECT_EQ(ask(feetech::recovery(1)), status(1, 0));
  EXPECT_EQ(read(1, 13, 1), Bytes{65});
  EXPECT_EQ(read(1, 5, 1), Bytes{1});
}

TEST_F(FeetechSim, MultiTurnWhenBothLimitsAreZeroAndResetStatusClearsTheTurns) {
  start({sts(1)});
  write(1, 9, {0, 0, 0, 0});
  write(1, 46, {0, 0});        // goal speed 0: the top speed
  write(1, 42, {0x68, 0x10});  // 4200: beyond one turn
  ASSERT_TRUE(reaches(1, 56, {0x68, 0x10}));
  host().send({0xFF, 0xFF, 0x01, 0x02, 0x0A, 0xF2});  // RESET STATUS, the worked frame
  EXPECT_EQ(host().receive_exactly(6), (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC}));
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x68, 0x00}));  // 4200 - 4096 = 104
  EXPECT_EQ(read(1, 66, 1), Bytes{0}) << "clearing the count does not move the servo";
}

TEST_F(FeetechSim, NegativeMultiTurnGoalIsSignMagnitude) {
  start({sts(1)});
  write(1, 9, {0, 0, 0, 0});
  write(1, 42, {0x64, 0x80});  // -100
  EXPECT_TRUE(reaches(1, 56, {0x64, 0x80}));
}

TEST_F(FeetechSim, CalibrateMakesThePresentPositionTheGivenValue) {
  start({sts(1)});
  host().send({0xFF, 0xFF, 0x01, 0x04, 0x0B, 0x00, 0x04, 0xEB});  // CALIBRATE -> 1024
  EXPECT_EQ(host().receive_exactly(6), (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC}));
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x00, 0x04}));
  EXPECT_EQ(read(1, 31, 2), (Bytes{0x00, 0x04})) << "offset +1024";
  EXPECT_EQ(read(1, 66, 1), Bytes{0});
}

TEST_F(FeetechSim, TorqueEnable128CalibratesTheMidPoint) {
  start({sts(1)});
  write(1, 42, {0xB8, 0x0B});  // 3000
  ASSERT_TRUE(reaches(1, 56, {0xB8, 0x0B}));
  write(1, 40, {128});
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x00, 0x08}));
  EXPECT_EQ(read(1, 31, 2), (Bytes{0xB8, 0x03})) << "offset 952 = 3000 - 2048";
  EXPECT_EQ(read(1, 40, 1), Bytes{0}) << "doc 001: the torque switch then reads 0";
}

TEST_F(FeetechSim, CalibrationIsKeptOverRebootWhateverTheLock) {
  start({sts(1)});
  write(1, 40, {128});
  EXPECT_TRUE(host().transact_all(kFeetechFormat, feetech::reboot(1)).empty());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x00, 0x08}));
}

TEST_F(FeetechSim, ConstantSpeedModeTurnsAtTheSignedGoalSpeed) {
  start({sts(1)});
  write(1, 33, {1});
  write(1, 46, {0x14, 0x80});  // -20 × 0.732 rpm (≈ -1000 steps/s), direction bit 15
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(read(1, 58, 2), (Bytes{0x14, 0x80}));
  EXPECT_EQ(read(1, 66, 1), Bytes{1});
  write(1, 46, {0, 0});
  EXPECT_EQ(read(1, 58, 2), (Bytes{0, 0}));
}

TEST_F(FeetechSim, PwmModeRunsOpenLoopOnGoalTime) {
  start({sts(1)});
  write(1, 33, {2});
  write(1, 44, {0xF4, 0x05});  // -500 (0.1 %), direction bit 10
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  const Bytes speed = read(1, 58, 2);
  ASSERT_EQ(speed.size(), 2U);
  EXPECT_NE(speed[1] & 0x80, 0) << "turning the negative way";
  EXPECT_GT(speed[0] | (speed[1] & 0x7F) << 8, 20) << "half the top speed (88 × 0.732 rpm)";
}

TEST_F(FeetechSim, StepModeMovesByEachGoalWritten) {
  start({sts(1)});
  write(1, 33, {3});
  write(1, 42, {0x00, 0x04});  // +1024
  ASSERT_TRUE(reaches(1, 56, {0x00, 0x0C}));
  write(1, 42, {0x00, 0x04});
  EXPECT_TRUE(reaches(1, 56, {0x00, 0x10}));  // 4096: no wrap, no limits in step mode
}

TEST_F(FeetechSim, TorqueOffStopsHoldingAndAGoalSwitchesItBackOn) {
  start({sts(1)});
  write(1, 40, {0});
  write(1, 42, {0x00, 0x09});
  EXPECT_EQ(read(1, 40, 1), Bytes{1});
  EXPECT_TRUE(reaches(1, 56, {0x00, 0x09}));
}

TEST_F(FeetechSim, InjectedErrorBitsShowInRepliesAndUnloadTheTorque) {
  start({sts(1)});
  rig->bus->set_error_bits(1, feetech::error_bit::kTemperature);
  EXPECT_EQ(ask(protocol::ping(1)), status(1, feetech::error_bit::kTemperature));
  EXPECT_EQ(read(1, 65, 1), Bytes{feetech::error_bit::kTemperature});
  const Bytes temperature = read(1, 63, 1);
  ASSERT_EQ(temperature.size(), 1U);
  EXPECT_GT(temperature[0], 70) << "above the max temperature (address 13)";
  EXPECT_EQ(read(1, 40, 1), Bytes{0}) << "unload conditions 44 include bit 2";
  rig->bus->set_error_bits(1, 0);
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0));
}

TEST_F(FeetechSim, ChangedIdAnswersUnderTheNewIdAfterTheReply) {
  start({sts(1)});
  EXPECT_EQ(ask(protocol::write(1, 5, Bytes{9})), status(1, 0));
  EXPECT_FALSE(host().transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  EXPECT_EQ(ask(protocol::ping(9)), status(9, 0));
}

TEST_F(FeetechSim, ChangedBaudAnswersAtTheNewRate) {
  start({sts(1)});
  EXPECT_EQ(ask(protocol::write(1, 6, Bytes{4})), status(1, 0));  // 115200
  EXPECT_FALSE(host().transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  host().set_baud(115'200);
  EXPECT_EQ(ask(protocol::ping(1)), status(1, 0));
}

// --- sms1 -------------------------------------------------------------------------------

TEST_F(FeetechSim, Sms1PowersUpWithTorqueOffAndAGoalSwitchesItOn) {
  start({sms1(1)});
  EXPECT_EQ(read(1, 40, 1), Bytes{0});
  write(1, 42, {0x00, 0x0A});  // 2560
  EXPECT_EQ(read(1, 40, 1), Bytes{1});
  EXPECT_EQ(read(1, 67, 2), (Bytes{0x00, 0x0A})) << "present goal";
  EXPECT_TRUE(reaches(1, 56, {0x00, 0x0A}));
}

TEST_F(FeetechSim, Sms1RegWriteFlagIsSetUntilAction) {
  start({sms1(1)});
  EXPECT_EQ(ask(protocol::reg_write(1, 42, Bytes{0x00, 0x09})), status(1, 0));
  EXPECT_EQ(read(1, 64, 1), Bytes{1});
  EXPECT_EQ(ask(protocol::action(1)), status(1, 0));
  EXPECT_EQ(read(1, 64, 1), Bytes{0});
  EXPECT_EQ(read(1, 42, 2), (Bytes{0x00, 0x09}));
}

TEST_F(FeetechSim, Sms1RunTimeSetsTheSpeedWhenRunSpeedIsZero) {
  start({sms1(1)});
  write(1, 44, {0xE8, 0x03});  // 1000 ms
  write(1, 42, {0x00, 0x0A});  // 512 steps away: ~512 steps/s
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const Bytes position = read(1, 56, 2);
  ASSERT_EQ(position.size(), 2U);
  const int present = position[0] | position[1] << 8;
  EXPECT_GT(present, 2048 + 100);
  EXPECT_LT(present, 2560 - 200);
}

TEST_F(FeetechSim, Sms1TorqueModeRunsOnRunTime) {
  start({sms1(1)});
  write(1, 35, {2});
  write(1, 40, {1});
  write(1, 44, {0x2C, 0x01});  // +300
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(read(1, 66, 1), Bytes{1});
}

TEST_F(FeetechSim, Sms1FirmwareDoesNotKnowCalibrate) {
  start({sms1(1)});
  // Answered with the status bits only (no Feetech error bit says "unknown instruction"), and
  // nothing calibrated.
  EXPECT_EQ(ask(feetech::calibrate(1, 1024)), status(1, 0));
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x00, 0x08}));
}

}  // namespace
}  // namespace sms::simulator::testing
