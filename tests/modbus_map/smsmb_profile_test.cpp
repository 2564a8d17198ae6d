// The smsmb profile (docs/PLC_GUIDE.md): SMSMB registers shown for sts / sms1 servos on feetech
// buses, each linked to its counterpart field with a conversion.
#include <gtest/gtest.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "modbus_map/register_map.h"
#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

using protocol::Bytes;

RegisterMap profile_of(TableId id) {
  auto map = RegisterMap::create(id, Profile::Smsmb);
  if (!map) throw std::runtime_error(map.error());
  return std::move(map).value();
}

template <typename T>
void expect_exception(const MapResult<T>& result, ModbusException code, const std::string& message_part = "") {
  ASSERT_FALSE(result) << "expected exception " << static_cast<int>(code);
  EXPECT_EQ(result.error().code, code) << result.error().message;
  EXPECT_NE(result.error().message.find(message_part), std::string::npos) << result.error().message;
}

MapResult<WritePlan> write(const RegisterMap& map, std::uint16_t start, std::vector<std::uint16_t> values) {
  return map.plan_register_write(start, values);
}

// Reads `count` registers at `start` and answers the plan's single READ with `bytes`.
std::vector<std::uint16_t> read(const RegisterMap& map, std::uint16_t start, std::uint16_t count,
                                BusRange expected_read, const Bytes& bytes) {
  const auto plan = map.plan_holding_read(start, count);
  if (!plan) throw std::runtime_error(plan.error().message);
  EXPECT_EQ(plan->reads, std::vector<BusRange>{expected_read});
  const std::vector<Bytes> replies{bytes};
  const auto values = map.registers_from(*plan, replies);
  if (!values) throw std::runtime_error(values.error().message);
  return *values;
}

TEST(SmsmbProfile, FeedbackInputRegistersComeFromTheStsPollBlock) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto plan = sts.plan_input_read(0x100, 8, default_poll_block(TableId::Sts));
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->source, ReadSource::PollCache);
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{56, 15}}));
  const std::vector<Bytes> cache{{
      0x64, 0x80,  // 56 present position -100 (sign bit 15)
      0x1A, 0x00,  // 58 present speed 26 × 0.732 rpm, the unit of both (factory phase)
      0x2C, 0x05,  // 60 present load -300 (sign bit 10)
      0x79,        // 62 12.1 V
      0x1E,        // 63 30 °C
      0x01,        // 64 REG WRITE flag (not in the SMSMB block)
      0x35,        // 65 status: voltage, temperature, unused bit 4, overload
      0x01,        // 66 moving
      0x00, 0x08,  // 67 present goal (not in the SMSMB block)
      0x64, 0x00,  // 69 current 100
  }};
  EXPECT_EQ(*sts.registers_from(*plan, cache), (std::vector<std::uint16_t>{0x25, 0xFF9C, 26, 0xFED4, 121, 30, 1, 100}));
}

TEST(SmsmbProfile, InputRegistersOutsideTheFeedbackBlockAre02) {
  const RegisterMap sts = profile_of(TableId::Sts);
  expect_exception(sts.plan_input_read(0x80, 1, default_poll_block(TableId::Sts)), ModbusException::IllegalDataAddress,
                   "0x100..0x107");
  // A configured poll block that leaves out present_current (69-70).
  expect_exception(sts.plan_input_read(0x100, 8, BusRange{56, 11}), ModbusException::IllegalDataAddress,
                   "present_current");
}

TEST(SmsmbProfile, ControlRegistersReadFromOneStsRead) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const Bytes bytes{
      0x01,                          // 40 torque enable
      0x0A,                          // 41 acceleration
      0xE8, 0x83,                    // 42 goal position -1000
      0x00, 0x00,                    // 44 goal time
      0x32, 0x00,                    // 46 goal speed 50 × 0.732 rpm, as on SMSMB
      0xF4, 0x01,                    // 48 torque limit 500
      0xAA, 0xAA, 0xAA, 0xAA, 0xAA,  // 50-54 no field
      0x00,                          // 55 lock
  };
  EXPECT_EQ(read(sts, 0x80, 7, {40, 16}, bytes), (std::vector<std::uint16_t>{0xFC18, 1, 10, 50, 500, 0, 0}));
}

TEST(SmsmbProfile, ControlRegisterWritesBecomeStsFramesWithoutGapBytes) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto plan = write(sts, 0x80, {0xFC18, 1, 10, 0xFFF6, 500, 0});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{
                              {40, {0x01, 0x0A, 0xE8, 0x83}},  // torque, accel, goal -1000 (0x83E8)
                              {46, {0x0A, 0x80, 0xF4, 0x01}},  // speed -10 (0x800A), limit 500
                              {55, {0x00}},                    // lock
                          }));
}

TEST(SmsmbProfile, Sms1CounterpartsSitElsewhere) {
  const RegisterMap sms1 = profile_of(TableId::Sms1);
  const auto calibration = write(sms1, 0x0F, {0xFF9C});  // -100 -> position correction 33, sign bit 11
  ASSERT_TRUE(calibration);
  EXPECT_EQ(calibration->writes, (std::vector<BusWrite>{{33, {0x64, 0x08}}}));
  const auto mode = write(sms1, 0x10, {1});
  ASSERT_TRUE(mode);
  EXPECT_EQ(mode->writes, (std::vector<BusWrite>{{35, {0x01}}}));
  const auto lock = write(sms1, 0x85, {0});
  ASSERT_TRUE(lock);
  EXPECT_EQ(lock->writes, (std::vector<BusWrite>{{48, {0x00}}}));
  EXPECT_EQ(read(sms1, 0x00, 1, {3, 2}, {0x01, 0x01}), std::vector<std::uint16_t>{0x0101});
}

TEST(SmsmbProfile, BaudCodeIsTranslatedThroughTheBitRate) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto rate_115200 = write(sts, 0x0B, {2});
  ASSERT_TRUE(rate_115200);
  EXPECT_EQ(rate_115200->writes, (std::vector<BusWrite>{{6, {0x04}}}));
  const auto rate_19200 = write(sts, 0x0B, {6});
  ASSERT_TRUE(rate_19200);
  EXPECT_EQ(rate_19200->writes, (std::vector<BusWrite>{{6, {0x08}}}));
  const auto rate_4800 = write(sts, 0x0B, {9});
  ASSERT_TRUE(rate_4800);
  EXPECT_EQ(rate_4800->writes, (std::vector<BusWrite>{{6, {0x0B}}}));
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0x04}), std::vector<std::uint16_t>{2});
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0x07}), std::vector<std::uint16_t>{5});  // 38400
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0x03}), std::vector<std::uint16_t>{1});  // 128000
}

TEST(SmsmbProfile, BaudRatesTheServoCannotRunAre03) {
  const RegisterMap sts = profile_of(TableId::Sts);
  expect_exception(write(sts, 0x0B, {0}), ModbusException::IllegalDataValue, "256000 bps): the servo cannot run");
  expect_exception(write(sts, 0x0B, {4}), ModbusException::IllegalDataValue, "56000 bps");
  expect_exception(write(sts, 0x0B, {10}), ModbusException::IllegalDataValue, "outside 0..9");
  // sms1 takes feetech codes 0-7 only: 19200 (code 8) is beyond it.
  expect_exception(write(profile_of(TableId::Sms1), 0x0B, {6}), ModbusException::IllegalDataValue, "codes 0..7");
}

TEST(SmsmbProfile, RatesWithoutAModbusCodeReadAsFFFF) {
  const RegisterMap sts = profile_of(TableId::Sts);
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0x00}), std::vector<std::uint16_t>{0xFFFF});  // 1 000 000
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0x05}), std::vector<std::uint16_t>{0xFFFF});  // 76 800
  EXPECT_EQ(read(sts, 0x0B, 1, {6, 1}, {0xC8}), std::vector<std::uint16_t>{0xFFFF});  // no such code
}

TEST(SmsmbProfile, FaultResetBit2CalibratesThroughTorqueEnable) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto centre = write(sts, 0x86, {0x0004});
  ASSERT_TRUE(centre);
  EXPECT_EQ(centre->writes, (std::vector<BusWrite>{{40, {0x80}}}));
  const auto centre_and_overload = write(sts, 0x86, {0x0005});
  ASSERT_TRUE(centre_and_overload);
  EXPECT_EQ(centre_and_overload->writes, (std::vector<BusWrite>{{40, {0x80}}}));
  const auto sms1 = write(profile_of(TableId::Sms1), 0x86, {0x0004});
  ASSERT_TRUE(sms1);
  EXPECT_EQ(sms1->writes, (std::vector<BusWrite>{{40, {0x80}}}));
}

TEST(SmsmbProfile, FaultResetOtherBitsNeedNoBusWrite) {
  const RegisterMap sts = profile_of(TableId::Sts);
  for (const std::uint16_t bits : {0x0000, 0x0001, 0x0002, 0x0020, 0x0040, 0x0080, 0x00E3}) {
    const auto plan = write(sts, 0x86, {bits});
    ASSERT_TRUE(plan) << bits;
    EXPECT_TRUE(plan->writes.empty()) << bits;
  }
  expect_exception(write(sts, 0x86, {0x0008}), ModbusException::IllegalDataValue, "undefined bits 0x08");
  expect_exception(write(sts, 0x86, {0x0100}), ModbusException::IllegalDataValue);
}

TEST(SmsmbProfile, OneRequestMayNotWriteAFieldTwice) {
  const RegisterMap sts = profile_of(TableId::Sts);
  // 0x81 torque switch and 0x86 bit 2 both land on torque enable (40).
  expect_exception(write(sts, 0x81, {1, 0, 0, 0, 0, 4}), ModbusException::IllegalDataValue, "0x81 and 0x86");
  EXPECT_TRUE(write(sts, 0x81, {1, 0, 0, 0, 0, 1}));  // bit 0 alone writes nothing
}

TEST(SmsmbProfile, ModesMapAndUnmatchedModesAre03) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto stepper = write(sts, 0x10, {4});
  ASSERT_TRUE(stepper);
  EXPECT_EQ(stepper->writes, (std::vector<BusWrite>{{33, {0x03}}}));
  expect_exception(write(sts, 0x10, {3}), ModbusException::IllegalDataValue, "accepted: 0, 1, 4");
  expect_exception(write(sts, 0x10, {2}), ModbusException::IllegalDataValue);
  EXPECT_EQ(read(sts, 0x10, 1, {33, 1}, {0x03}), std::vector<std::uint16_t>{4});
  EXPECT_EQ(read(sts, 0x10, 1, {33, 1}, {0x02}), std::vector<std::uint16_t>{2});  // open-loop PWM
  EXPECT_EQ(read(sts, 0x10, 1, {33, 1}, {0x01}), std::vector<std::uint16_t>{1});
  expect_exception(write(profile_of(TableId::Sms1), 0x10, {4}), ModbusException::IllegalDataValue);
}

TEST(SmsmbProfile, LockUnlockingTheFactoryAreaMeansPersist) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto unlock = write(sts, 0x85, {128});
  ASSERT_TRUE(unlock);
  EXPECT_EQ(unlock->writes, (std::vector<BusWrite>{{55, {0x00}}}));
  expect_exception(write(sts, 0x85, {2}), ModbusException::IllegalDataValue);
  EXPECT_EQ(read(sts, 0x85, 1, {55, 1}, {0x00}), std::vector<std::uint16_t>{0});
  EXPECT_EQ(read(sts, 0x85, 1, {55, 1}, {0x01}), std::vector<std::uint16_t>{1});
}

TEST(SmsmbProfile, ScaledRegistersRoundHalfAwayFromZero) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto delay = write(sts, 0x0C, {101});  // 101 µs -> 50.5 -> 51 × 2 µs
  ASSERT_TRUE(delay);
  EXPECT_EQ(delay->writes, (std::vector<BusWrite>{{7, {0x33}}}));
  expect_exception(write(sts, 0x0C, {501}), ModbusException::IllegalDataValue, "outside 0..500");
  EXPECT_EQ(read(sts, 0x0C, 1, {7, 1}, {0xFA}), std::vector<std::uint16_t>{500});
  // sms1 speeds are 0.087 °/s: 50 of them make SMSMB's 0.732 rpm.
  const RegisterMap sms1 = profile_of(TableId::Sms1);
  const auto fastest = write(sms1, 0x83, {655});  // 655 × 50 = 32750
  ASSERT_TRUE(fastest);
  EXPECT_EQ(fastest->writes, (std::vector<BusWrite>{{46, {0xEE, 0x7F}}}));
  expect_exception(write(sms1, 0x83, {656}), ModbusException::IllegalDataValue, "outside -655..655");
  EXPECT_EQ(read(sms1, 0x102, 1, {58, 2}, {0x19, 0x80}), std::vector<std::uint16_t>{0xFFFF});  // -25 -> -1
  EXPECT_EQ(read(sms1, 0x102, 1, {58, 2}, {0x18, 0x00}), std::vector<std::uint16_t>{0});       // 24 -> 0
  const auto torque = write(sts, 0x190, {205});                                                // 20.5 % -> 21 %
  ASSERT_TRUE(torque);
  EXPECT_EQ(torque->writes, (std::vector<BusWrite>{{34, {0x15}}}));
  EXPECT_EQ(read(sts, 0x18F, 1, {38, 1}, {0xC8}), std::vector<std::uint16_t>{2000});  // 200 × 10 ms
}

TEST(SmsmbProfile, VersionRegistersJoinTwoStsBytes) {
  const RegisterMap sts = profile_of(TableId::Sts);
  // firmware 2.48, model 8.42 (doc 001 §15); 2 is no field.
  EXPECT_EQ(read(sts, 0x00, 4, {0, 5}, {0x02, 0x30, 0xAA, 0x08, 0x2A}),
            (std::vector<std::uint16_t>{0x0230, 0x082A, 0, 0}));
}

TEST(SmsmbProfile, RegistersWithoutCounterpartAre02AloneAndZeroInsideAReadRange) {
  const RegisterMap sms1 = profile_of(TableId::Sms1);
  expect_exception(sms1.plan_holding_read(0x14, 1), ModbusException::IllegalDataAddress,
                   "speed_p_gain (0x14) has no counterpart in table sms1");
  expect_exception(profile_of(TableId::Sts).plan_holding_read(0x02, 2), ModbusException::IllegalDataAddress,
                   "firmware_year");
  EXPECT_EQ(read(sms1, 0x11, 5, {21, 3}, {0x0F, 0x00, 0x01}), (std::vector<std::uint16_t>{15, 0, 1, 0, 0}));
  expect_exception(write(sms1, 0x14, {1}), ModbusException::IllegalDataAddress, "no counterpart");
  expect_exception(write(sms1, 0x11, {1, 2, 3, 4, 5}), ModbusException::IllegalDataAddress, "speed_p_gain");
  expect_exception(write(sms1, 0x82, {1}), ModbusException::IllegalDataAddress, "acceleration (0x82)");
}

TEST(SmsmbProfile, ReadOnlyCounterpartsRefuseWrites) {
  const RegisterMap sts = profile_of(TableId::Sts);
  expect_exception(write(sts, 0x100, {0}), ModbusException::IllegalDataAddress, "read-only");
  // The phase byte is writable on both (Feetech wiki memory-sts: RW, "change with care").
  const auto sts_phase = write(sts, 0x188, {4});
  ASSERT_TRUE(sts_phase);
  EXPECT_EQ(sts_phase->writes, (std::vector<BusWrite>{{18, {0x04}}}));
  const auto sms1_phase = write(profile_of(TableId::Sms1), 0x188, {1});
  ASSERT_TRUE(sms1_phase);
  EXPECT_EQ(sms1_phase->writes, (std::vector<BusWrite>{{18, {0x01}}}));
}

TEST(SmsmbProfile, RangesAreTheSmsmbRangeCutToTheCounterpart) {
  const RegisterMap sts = profile_of(TableId::Sts);
  expect_exception(write(sts, 0x0A, {0}), ModbusException::IllegalDataValue, "outside 1..247");
  expect_exception(write(sts, 0x0A, {248}), ModbusException::IllegalDataValue);
  expect_exception(write(sts, 0x81, {128}), ModbusException::IllegalDataValue, "outside 0..1");
  expect_exception(write(sts, 0x80, {0x8800}), ModbusException::IllegalDataValue, "outside -30719..30719");
  expect_exception(write(sts, 0x0F, {2048}), ModbusException::IllegalDataValue);
  const auto id = write(sts, 0x0A, {7});
  ASSERT_TRUE(id);
  EXPECT_EQ(id->writes, (std::vector<BusWrite>{{5, {0x07}}}));
}

TEST(SmsmbProfile, StagedWritesGoToTheCounterpart) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto plan = write(sts, 512 + 0x80, {0xFC18});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_TRUE(plan->staged);
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{42, {0xE8, 0x83}}}));
}

TEST(SmsmbProfile, CoilsAndDiscreteInputsAtSmsmbAddresses) {
  const RegisterMap sts = profile_of(TableId::Sts);
  const auto on = sts.plan_coil_write(0x81, {true});
  ASSERT_TRUE(on);
  EXPECT_EQ(on->writes, (std::vector<BusWrite>{{40, {0x01}}}));
  const auto coil = sts.plan_coil_read(0x81, 1);
  ASSERT_TRUE(coil);
  ASSERT_EQ(coil->reads, (std::vector<BusRange>{{40, 1}}));
  const std::vector<Bytes> torque_on{{0x01}};
  EXPECT_EQ(*sts.bits_from(*coil, torque_on), std::vector<bool>{true});
  const auto moving = sts.plan_discrete_read(0x106, 1, default_poll_block(TableId::Sts));
  ASSERT_TRUE(moving);
  EXPECT_EQ(moving->source, ReadSource::PollCache);
  EXPECT_EQ(moving->reads, (std::vector<BusRange>{{66, 1}}));
  expect_exception(sts.plan_coil_write(0x85, {true}), ModbusException::IllegalDataAddress);  // lock: 0/1/128
}

TEST(SmsmbProfile, LinksAreDataNamingRealFields) {
  EXPECT_EQ(smsmb_links(TableId::D55d).size(), 0u);
  EXPECT_EQ(smsmb_links(TableId::Smsmb).size(), 0u);
  const RegisterMap sts = profile_of(TableId::Sts);
  const RegisterEntry* speed = sts.entry_at(0x83);
  ASSERT_NE(speed, nullptr);
  EXPECT_EQ(speed->counterpart->name, "goal_speed");
  EXPECT_NE(speed->link->conversion, Conversion::Scale) << "0.732 rpm on both";
  const RegisterMap sms1 = profile_of(TableId::Sms1);
  const RegisterEntry* sms1_speed = sms1.entry_at(0x83);
  ASSERT_NE(sms1_speed, nullptr);
  EXPECT_EQ(sms1_speed->counterpart->name, "run_speed");
  EXPECT_EQ(sms1_speed->link->conversion, Conversion::Scale);
  EXPECT_EQ(sms1_speed->min, -655);
  EXPECT_EQ(sms1_speed->max, 655);
  EXPECT_EQ(sts.entry_at(0x14)->counterpart->addr, 37);
  EXPECT_EQ(sts.entry_at(0x15)->counterpart->addr, 39);
  EXPECT_EQ(sts.entry_at(0x180)->counterpart, nullptr);
  EXPECT_EQ(profile_of(TableId::Sms1).entry_at(0x0F)->counterpart->addr, 33);
  EXPECT_EQ(sts.description(), "smsmb profile of table sts");
}

}  // namespace
}  // namespace sms::modbus_map
