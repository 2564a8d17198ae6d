// The rules of docs/PLC_GUIDE.md on the native profile: read plans, assembly, write frames, coils,
// discrete inputs, staged writes and every exception rule.
#include "modbus_map/register_map.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <stdexcept>
#include <string>
#include <vector>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

using protocol::Bytes;

RegisterMap make(TableId id, Profile profile = Profile::Native, std::optional<ByteOrder> order = std::nullopt) {
  auto map = RegisterMap::create(id, profile, order);
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

// --- reads -----------------------------------------------------------------------------------------

TEST(HoldingRead, OneBusReadCoversTheRangeAndGapsReadZero) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = sts.plan_holding_read(40, 10);  // 40..49
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->source, ReadSource::Bus);
  // 40 torque, 41 accel, 42-43 goal, 44-45 time, 46-47 speed, 48-49 torque limit
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{40, 10}}));
  const std::vector<Bytes> replies{{0x01, 0x0A, 0xE8, 0x83, 0x00, 0x00, 0xC4, 0x09, 0xE8, 0x03}};
  const auto values = sts.registers_from(*plan, replies);
  ASSERT_TRUE(values) << values.error().message;
  EXPECT_EQ(*values, (std::vector<std::uint16_t>{1, 10, 0xFC18, 0, 0, 0, 2500, 0, 1000, 0}));
}

TEST(HoldingRead, StartingOnASecondByteReadsItAsZero) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = sts.plan_holding_read(43, 2);  // second byte of 42, goal_time
  ASSERT_TRUE(plan);
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{44, 2}}));
  const std::vector<Bytes> replies{{0xF4, 0x05}};
  EXPECT_EQ(*sts.registers_from(*plan, replies), (std::vector<std::uint16_t>{0, 0xFE0C}));
}

TEST(HoldingRead, OnlyGapsReadZerosWithoutBusTraffic) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = sts.plan_holding_read(50, 5);  // 50..54: no fields
  ASSERT_TRUE(plan);
  EXPECT_TRUE(plan->reads.empty());
  EXPECT_EQ(*sts.registers_from(*plan, {}), (std::vector<std::uint16_t>{0, 0, 0, 0, 0}));
}

TEST(HoldingRead, WriteOnlyFieldsReadZeroAndAreNotRead) {
  const RegisterMap d55d = make(TableId::D55d);
  const auto plan = d55d.plan_holding_read(18, 3);  // 18 unload, 19 W, 20 termination
  ASSERT_TRUE(plan);
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{18, 3}}));
  const std::vector<Bytes> replies{{0x7F, 0x02, 0x01}};
  EXPECT_EQ(*d55d.registers_from(*plan, replies), (std::vector<std::uint16_t>{0x7F, 0, 1}));
}

TEST(HoldingRead, ByteOrderOverrideReadsHighByteFirst) {
  const RegisterMap sms1 = make(TableId::Sms1, Profile::Native, ByteOrder::HighFirst);
  const auto plan = sms1.plan_holding_read(11, 1);
  ASSERT_TRUE(plan);
  const std::vector<Bytes> replies{{0x0F, 0xFF}};  // doc 000's printed default, high byte first
  EXPECT_EQ(*sms1.registers_from(*plan, replies), std::vector<std::uint16_t>{4095});
}

TEST(HoldingRead, ModbusRtuServoGetsOneReadPerRunOfRegisters) {
  const RegisterMap smsmb = make(TableId::Smsmb);
  const auto plan = smsmb.plan_holding_read(0x00, 0x16);  // 0x00-0x03, gap, 0x0A-0x15
  ASSERT_TRUE(plan);
  EXPECT_EQ(plan->reads, (std::vector<BusRange>{{0x00, 4}, {0x0A, 12}}));
  // fault_reset (0x86) is write-only: not read, reads 0.
  const auto control = smsmb.plan_holding_read(0x80, 7);
  ASSERT_TRUE(control);
  EXPECT_EQ(control->reads, (std::vector<BusRange>{{0x80, 6}}));
  const std::vector<Bytes> replies{{0xFC, 0x18, 0x00, 0x01, 0x00, 0x0A, 0xFF, 0x9C, 0x03, 0xE8, 0x00, 0x01}};
  EXPECT_EQ(*smsmb.registers_from(*control, replies), (std::vector<std::uint16_t>{0xFC18, 1, 10, 0xFF9C, 1000, 1, 0}));
}

TEST(HoldingRead, RepliesOfTheWrongLengthAreADeviceFailure) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = sts.plan_holding_read(56, 2);
  ASSERT_TRUE(plan);
  const std::vector<Bytes> short_reply{{0x18}};
  expect_exception(sts.registers_from(*plan, short_reply), ModbusException::ServerDeviceFailure,
                   "answered 1 bytes to a READ of 2 at 56");
  expect_exception(sts.registers_from(*plan, {}), ModbusException::ServerDeviceFailure);
}

// --- input registers and discrete inputs (poll cache) ------------------------------------------

TEST(InputRead, ServesThePollBlockFromTheCache) {
  const RegisterMap sts = make(TableId::Sts);
  const BusRange block = default_poll_block(TableId::Sts);
  EXPECT_EQ(block, (BusRange{56, 15}));
  const auto plan = sts.plan_input_read(56, 15, block);
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->source, ReadSource::PollCache);
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{56, 15}}));
  // position 2047, 12.1 V, 30 °C, moving, current 100 × 6.5 mA
  const std::vector<Bytes> cache{
      {0xFF, 0x07, 0x00, 0x00, 0x00, 0x00, 0x79, 0x1E, 0x00, 0x00, 0x01, 0x00, 0x00, 0x64, 0x00}};
  EXPECT_EQ(*sts.registers_from(*plan, cache),
            (std::vector<std::uint16_t>{2047, 0, 0, 0, 0, 0, 121, 30, 0, 0, 1, 0, 0, 100, 0}));
}

TEST(InputRead, OutsideThePollBlockIsIllegalAddress) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(sts.plan_input_read(55, 1, default_poll_block(TableId::Sts)), ModbusException::IllegalDataAddress,
                   "read holding registers (FC03)");
  // A configured block without present_current's second byte.
  expect_exception(sts.plan_input_read(69, 1, BusRange{56, 14}), ModbusException::IllegalDataAddress);
}

TEST(InputRead, ModbusRtuServoUsesOneCacheRangeAcrossRegisters) {
  const RegisterMap smsmb = make(TableId::Smsmb);
  const auto plan = smsmb.plan_input_read(0x101, 2, default_poll_block(TableId::Smsmb));
  ASSERT_TRUE(plan);
  EXPECT_EQ(plan->reads, (std::vector<BusRange>{{0x101, 2}}));
  const std::vector<Bytes> cache{{0x08, 0x00, 0xFF, 0xF6}};
  EXPECT_EQ(*smsmb.registers_from(*plan, cache), (std::vector<std::uint16_t>{2048, 0xFFF6}));
}

TEST(DiscreteRead, ComesFromTheCacheWhenPolledElseFromTheServo) {
  const RegisterMap d55d = make(TableId::D55d);
  const auto cached = d55d.plan_discrete_read(42, 3, default_poll_block(TableId::D55d));
  ASSERT_TRUE(cached);
  EXPECT_EQ(cached->source, ReadSource::PollCache);
  ASSERT_EQ(cached->reads, (std::vector<BusRange>{{42, 3}}));
  // 42 moving, 43 brake (a coil, not a discrete input), 44 REG WRITE pending
  const std::vector<Bytes> bytes{{0x01, 0x01, 0x01}};
  EXPECT_EQ(*d55d.bits_from(*cached, bytes), (std::vector<bool>{true, false, true}));
  const auto live = d55d.plan_discrete_read(42, 3, std::nullopt);
  ASSERT_TRUE(live);
  EXPECT_EQ(live->source, ReadSource::Bus);
  const auto outside = d55d.plan_discrete_read(42, 1, BusRange{0, 10});
  ASSERT_TRUE(outside);
  EXPECT_EQ(outside->source, ReadSource::Bus);
}

TEST(DiscreteRead, ARangeWithoutDiscreteInputsIsIllegalAddress) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(sts.plan_discrete_read(40, 20, std::nullopt), ModbusException::IllegalDataAddress,
                   "discrete inputs: 66 moving");
}

// --- coils -------------------------------------------------------------------------------------------

TEST(CoilRead, ReadsBooleanFieldsLiveOthersAsZero) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = sts.plan_coil_read(40, 16);  // 40 torque enable .. 55 lock
  ASSERT_TRUE(plan);
  EXPECT_EQ(plan->source, ReadSource::Bus);
  ASSERT_EQ(plan->reads, (std::vector<BusRange>{{40, 16}}));
  Bytes bytes(16, 0x07);  // every other byte non-zero: they are no coils and read 0
  bytes[0] = 0x01;
  bytes[15] = 0x00;
  const std::vector<Bytes> replies{bytes};
  std::vector<bool> expected(16, false);
  expected[0] = true;
  EXPECT_EQ(*sts.bits_from(*plan, replies), expected);
}

TEST(CoilRead, ARangeWithoutCoilsIsIllegalAddressAndListsTheCoils) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(sts.plan_coil_read(41, 3), ModbusException::IllegalDataAddress, "coils: 40 torque_enable, 55 lock");
}

TEST(CoilWrite, WritesOneOrZero) {
  const RegisterMap d55d = make(TableId::D55d);
  const auto on = d55d.plan_coil_write(43, {true});
  ASSERT_TRUE(on);
  EXPECT_EQ(on->writes, (std::vector<BusWrite>{{43, {0x01}}}));
  const auto off = d55d.plan_coil_write(47, {false});
  ASSERT_TRUE(off);
  EXPECT_EQ(off->writes, (std::vector<BusWrite>{{47, {0x00}}}));
}

TEST(CoilWrite, EveryAddressMustBeACoil) {
  const RegisterMap d55d = make(TableId::D55d);
  expect_exception(d55d.plan_coil_write(43, {true, false}), ModbusException::IllegalDataAddress, "coil 44");
  expect_exception(d55d.plan_coil_write(42, {true}), ModbusException::IllegalDataAddress);  // discrete input
  expect_exception(d55d.plan_coil_write(45, {true}), ModbusException::IllegalDataAddress);  // gap
}

// --- writes ------------------------------------------------------------------------------------------

TEST(RegisterWrite, SignMagnitudeGoesOnTheBusWithItsDirectionBit) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = write(sts, 46, {0xFC18});  // goal speed -1000
  ASSERT_TRUE(plan);
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{46, {0xE8, 0x83}}}));  // 0x83E8
  const auto high_first = write(make(TableId::Sts, Profile::Native, ByteOrder::HighFirst), 46, {0xFC18});
  ASSERT_TRUE(high_first);
  EXPECT_EQ(high_first->writes, (std::vector<BusWrite>{{46, {0x83, 0xE8}}}));
}

TEST(RegisterWrite, ContiguousFieldsShareOneFrame) {
  const RegisterMap sts = make(TableId::Sts);
  // 40 torque 1, 41 accel 10, 42 goal -1000, 43 (second byte: ignored), 44 time 0, 45 ignored,
  // 46 speed 2500 -> one WRITE 40..47 (docs/PROTOCOL.md §1.1 writes 42..47 the same way).
  const auto plan = write(sts, 40, {1, 10, 0xFC18, 0xBEEF, 0, 0xBEEF, 2500});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{40, {0x01, 0x0A, 0xE8, 0x83, 0x00, 0x00, 0xC4, 0x09}}}));
}

TEST(RegisterWrite, GapsSplitFramesAndAreNeverWritten) {
  const RegisterMap sts = make(TableId::Sts);
  // 48 torque limit, 49 second byte, 50-54 gaps (values ignored), 55 lock
  const auto plan = write(sts, 48, {500, 7, 7, 7, 7, 7, 7, 0});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{48, {0xF4, 0x01}}, {55, {0x00}}}));
}

TEST(RegisterWrite, ModbusRtuServoGetsRegistersHighByteFirst) {
  const RegisterMap smsmb = make(TableId::Smsmb);
  const auto plan = write(smsmb, 0x80, {0x0800, 1, 20});
  ASSERT_TRUE(plan);
  // docs/PROTOCOL.md §1.3 worked frame: 01 06 00 80 08 00 sets goal position 2048.
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{0x80, {0x08, 0x00, 0x00, 0x01, 0x00, 0x14}}}));
}

TEST(RegisterWrite, FieldBytesForSyncGroups) {
  const RegisterMap sts = make(TableId::Sts);
  const auto bytes = sts.field_bytes(*field_at(sts.servo_table(), 42), 0xFC18);
  ASSERT_TRUE(bytes);
  EXPECT_EQ(*bytes, (Bytes{0xE8, 0x83}));
  expect_exception(sts.field_bytes(*field_at(sts.servo_table(), 42), 30720), ModbusException::IllegalDataValue);
}

// --- staged writes (512 + a) -----------------------------------------------------------------------

TEST(StagedWrite, BecomesOneRegWriteFrame) {
  const RegisterMap sts = make(TableId::Sts);
  const auto plan = write(sts, 512 + 42, {2048, 0, 0, 0, 1000});  // 42..46: goal, time, speed
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_TRUE(plan->staged);
  EXPECT_EQ(plan->writes, (std::vector<BusWrite>{{42, {0x00, 0x08, 0x00, 0x00, 0xE8, 0x03}}}));
}

TEST(StagedWrite, MustBeOneContiguousRun) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(write(sts, 512 + 48, {500, 0, 0, 0, 0, 0, 7, 0}), ModbusException::IllegalDataAddress,
                   "one contiguous run");
}

TEST(StagedWrite, ExistsOnPacketBusesOnly) {
  const RegisterMap smsmb = make(TableId::Smsmb);
  expect_exception(write(smsmb, 512 + 0x80, {0}), ModbusException::IllegalDataAddress, "packet buses only");
  EXPECT_FALSE(smsmb.supports_staged_writes());
  EXPECT_TRUE(make(TableId::D55d).supports_staged_writes());
}

// --- exception rules of docs/PLC_GUIDE.md ------------------------------------------------------------

TEST(Exceptions, AddressBeyondTheTableIs02) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(sts.plan_holding_read(71, 1), ModbusException::IllegalDataAddress, "last address 70");
  expect_exception(sts.plan_holding_read(69, 3), ModbusException::IllegalDataAddress);
  expect_exception(write(sts, 71, {0}), ModbusException::IllegalDataAddress);
  expect_exception(write(sts, 300, {0}), ModbusException::IllegalDataAddress);
  expect_exception(sts.plan_coil_read(55, 20), ModbusException::IllegalDataAddress);
  expect_exception(write(sts, 512 + 71, {0}), ModbusException::IllegalDataAddress);
  // Staged addresses are written, not read.
  expect_exception(sts.plan_holding_read(512 + 42, 1), ModbusException::IllegalDataAddress);
}

TEST(Exceptions, WriteToAReadOnlyFieldIs02EvenInsideALongerWrite) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(write(sts, 56, {0}), ModbusException::IllegalDataAddress,
                   "present_position (56) of table sts is read-only");
  expect_exception(write(sts, 55, {0, 0}), ModbusException::IllegalDataAddress, "read-only");
}

TEST(Exceptions, WriteTouchingOnlyGapsOrSecondBytesIs02) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(write(sts, 53, {0}), ModbusException::IllegalDataAddress, "touches no field");
  expect_exception(write(sts, 50, {0, 0, 0}), ModbusException::IllegalDataAddress, "touches no field");
  expect_exception(write(sts, 43, {0}), ModbusException::IllegalDataAddress, "second byte of goal_position (42)");
  expect_exception(write(sts, 49, {0, 0}), ModbusException::IllegalDataAddress, "second byte of torque_limit (48)");
}

TEST(Exceptions, SecondByteWithoutItsFirstIsRefusedInsideALongerWrite) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(write(sts, 43, {0, 0, 0}), ModbusException::IllegalDataAddress, "second byte of goal_position");
}

TEST(Exceptions, AQuantityOfZeroOrOverTheModbusLimitsIs03) {
  const RegisterMap smsmb = make(TableId::Smsmb);
  EXPECT_TRUE(smsmb.plan_holding_read(0x100, 125));
  expect_exception(smsmb.plan_holding_read(0x100, 126), ModbusException::IllegalDataValue, "1..125");
  expect_exception(smsmb.plan_holding_read(0x100, 0), ModbusException::IllegalDataValue);
  expect_exception(smsmb.plan_register_write(0x100, std::vector<std::uint16_t>(124, 0)),
                   ModbusException::IllegalDataValue, "1..123");
  expect_exception(smsmb.plan_register_write(0x100, {}), ModbusException::IllegalDataValue);
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(sts.plan_coil_read(0, 2001), ModbusException::IllegalDataValue, "1..2000");
  expect_exception(sts.plan_coil_write(0, std::vector<bool>(1969, false)), ModbusException::IllegalDataValue,
                   "1..1968");
}

TEST(Exceptions, ValueOutsideTheRangeIs03) {
  const RegisterMap sts = make(TableId::Sts);
  expect_exception(write(sts, 13, {300}), ModbusException::IllegalDataValue,
                   "max_temperature (13) of table sts is outside 0..100");
  expect_exception(write(sts, 31, {5000}), ModbusException::IllegalDataValue, "outside -2047..2047");
  expect_exception(write(sts, 42, {30720}), ModbusException::IllegalDataValue);
  expect_exception(write(sts, 16, {0xFFFF}), ModbusException::IllegalDataValue, "value 65535");
  expect_exception(write(sts, 40, {3}), ModbusException::IllegalDataValue, "not one of 0 1 2 128");
  EXPECT_TRUE(write(sts, 40, {2}));  // damping (wiki memory-sts)
  EXPECT_TRUE(write(sts, 40, {128}));
}

TEST(Exceptions, AddressErrorsWinOverValueErrors) {
  const RegisterMap sts = make(TableId::Sts);
  // 56 has a bad value (no: it is read-only), 55 gets 300: 0x02, as a Modbus server checks
  // addresses first.
  expect_exception(write(sts, 55, {300, 0}), ModbusException::IllegalDataAddress, "present_position");
}

TEST(Profiles, NamesAndUnsupportedCombinations) {
  EXPECT_EQ(profile_from_name("smsmb"), Profile::Smsmb);
  EXPECT_EQ(profile_from_name("native"), Profile::Native);
  EXPECT_EQ(profile_from_name("SMSMB"), std::nullopt);
  EXPECT_EQ(to_string(Profile::Smsmb), "smsmb");
  EXPECT_FALSE(RegisterMap::create(TableId::D55d, Profile::Smsmb));
  const auto smsmb_twice = RegisterMap::create(TableId::Smsmb, Profile::Smsmb);
  ASSERT_FALSE(smsmb_twice);
  EXPECT_NE(smsmb_twice.error().find("already is the SMSMB map"), std::string::npos);
  EXPECT_FALSE(RegisterMap::create(TableId::Smsmb, Profile::Native, ByteOrder::LowFirst));
  EXPECT_TRUE(RegisterMap::create(TableId::Smsmb, Profile::Native, ByteOrder::HighFirst));
  EXPECT_EQ(to_string(ModbusException::GatewayTargetFailedToRespond), "gateway target device failed to respond");
}

TEST(PollBlocks, DefaultsAndConfiguredFields) {
  EXPECT_EQ(default_poll_block(TableId::Sms1), (BusRange{56, 15}));
  EXPECT_EQ(default_poll_block(TableId::D55d), (BusRange{36, 14}));
  EXPECT_EQ(default_poll_block(TableId::Smsmb), (BusRange{0x100, 8}));
  const std::vector<std::string> fields{"moving", "present_position"};
  EXPECT_EQ(*poll_block_for_fields(TableId::Sts, fields), (BusRange{56, 11}));
  const std::vector<std::string> registers{"present_speed", "present_current"};
  EXPECT_EQ(*poll_block_for_fields(TableId::Smsmb, registers), (BusRange{0x102, 6}));
  const std::vector<std::string> unknown{"present_position", "position"};
  const auto error = poll_block_for_fields(TableId::Sts, unknown);
  ASSERT_FALSE(error);
  EXPECT_NE(error.error().find("table sts has no field 'position' to poll"), std::string::npos) << error.error();
  const std::vector<std::string> write_only{"clear_unload_condition"};
  EXPECT_FALSE(poll_block_for_fields(TableId::D55d, write_only));
}

// Every readable field of every table and profile, read live in runs the map accepts: each run one
// FC03 of at most 125 registers, together every field once (an smsmb table needs several: its
// gaps answer 0x02).
TEST(LiveReadRuns, CoverEveryReadableFieldInRunsTheMapAccepts) {
  for (const TableId id : {TableId::Sts, TableId::Sms1, TableId::D55d, TableId::Smsmb, TableId::Scs}) {
    for (const Profile profile : {Profile::Native, Profile::Smsmb}) {
      if (profile == Profile::Smsmb && (id == TableId::D55d || id == TableId::Smsmb || id == TableId::Scs)) continue;
      const RegisterMap map = make(id, profile);
      std::vector<const RegisterEntry*> readable;
      for (const RegisterEntry& entry : map.entries()) {
        if (entry.readable && entry.address < kStagedWriteBase) readable.push_back(&entry);
      }
      const auto runs = map.live_read_runs(readable);
      std::size_t covered = 0;
      for (const BusRange& run : runs) {
        EXPECT_LE(run.count, 125) << map.description();
        EXPECT_TRUE(map.plan_holding_read(run.address, run.count)) << map.description() << " " << run.address;
      }
      for (const RegisterEntry* entry : readable) {
        covered += std::count_if(runs.begin(), runs.end(), [&](const BusRange& run) {
          return entry->address >= run.address && entry->address < run.end();
        });
      }
      EXPECT_EQ(covered, readable.size()) << map.description();
      if (id == TableId::Smsmb) {
        EXPECT_GT(runs.size(), 1U) << "smsmb's gaps";
      }
    }
  }
}

}  // namespace
}  // namespace sms::modbus_map
