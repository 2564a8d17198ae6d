#include "modbus_map/tables.h"

#include <gtest/gtest.h>

#include <array>
#include <stdexcept>
#include <vector>

namespace sms::modbus_map {
namespace {

// --- the compile-time checks ---------------------------------------------------------------------

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
constexpr std::array kOverlapping{
    FieldSpec{.addr = 10, .name = "a", .size = 2, .max = 1},
    FieldSpec{.addr = 11, .name = "b", .size = 1, .max = 1},  // 11 is a's second byte
};
constexpr std::array kUnsorted{
    FieldSpec{.addr = 12, .name = "a", .size = 1, .max = 1},
    FieldSpec{.addr = 10, .name = "b", .size = 1, .max = 1},
};
constexpr std::array kAdjacent{
    FieldSpec{.addr = 10, .name = "a", .size = 2, .max = 1},
    FieldSpec{.addr = 12, .name = "b", .size = 1, .max = 1},
};
constexpr std::array kOneByteRegister{FieldSpec{.addr = 0, .name = "a", .size = 1, .max = 1}};
constexpr std::array kDuplicateName{
    FieldSpec{.addr = 0, .name = "a", .size = 1, .max = 1},
    FieldSpec{.addr = 1, .name = "a", .size = 1, .max = 1},
};
constexpr std::array kDefaultOutsideRange{FieldSpec{.addr = 0, .name = "a", .size = 1, .default_value = 5, .max = 4}};
constexpr std::array kSignBitOutsideField{
    FieldSpec{.addr = 0, .name = "a", .size = 1, .encoding = sign_magnitude(10), .min = -1, .max = 1}};
constexpr std::array kRangeTooWideForBit{
    FieldSpec{.addr = 0, .name = "a", .size = 2, .encoding = sign_magnitude(11), .min = -5000, .max = 5000}};
constexpr std::array kCoilOnReadOnly{
    FieldSpec{.addr = 0, .name = "a", .size = 1, .access = Access::ReadOnly, .max = 1, .bit_space = BitSpace::Coil}};
#pragma GCC diagnostic pop

static_assert(!fields_sorted_and_disjoint(kOverlapping, Addressing::Byte));
static_assert(!fields_sorted_and_disjoint(kUnsorted, Addressing::Byte));
static_assert(fields_sorted_and_disjoint(kAdjacent, Addressing::Byte));
static_assert(!fields_sorted_and_disjoint(kOneByteRegister, Addressing::Register));
static_assert(!fields_well_formed(kDuplicateName));
static_assert(!fields_well_formed(kDefaultOutsideRange));
static_assert(!fields_well_formed(kSignBitOutsideField));
static_assert(!fields_well_formed(kRangeTooWideForBit));
static_assert(!fields_well_formed(kCoilOnReadOnly));

TEST(TableChecks, RejectOverlapDisorderAndInconsistentFields) {
  EXPECT_FALSE(fields_sorted_and_disjoint(kOverlapping, Addressing::Byte));
  EXPECT_FALSE(fields_sorted_and_disjoint(kUnsorted, Addressing::Byte));
  EXPECT_TRUE(fields_sorted_and_disjoint(kAdjacent, Addressing::Byte));
  EXPECT_FALSE(fields_well_formed(kDuplicateName));
  EXPECT_FALSE(fields_well_formed(kRangeTooWideForBit));
}

TEST(TableChecks, EveryShippedTablePassesThem) {
  for (const TableSpec* spec : all_tables()) {
    EXPECT_TRUE(fields_sorted_and_disjoint(spec->fields, spec->addressing)) << spec->name;
    EXPECT_TRUE(fields_well_formed(spec->fields)) << spec->name;
  }
}

// --- the tables --------------------------------------------------------------------------------

TEST(Tables, AreFoundByIdAndName) {
  ASSERT_EQ(all_tables().size(), 5u);
  EXPECT_EQ(table(TableId::Scs).name, "scs");
  EXPECT_EQ(table_from_name("scs"), TableId::Scs);
  EXPECT_EQ(table(TableId::Scs).default_byte_order, ByteOrder::HighFirst);  // SCSCL SDK End = 1
  EXPECT_FALSE(table(TableId::Scs).has_sync_read);
  EXPECT_EQ(table(TableId::Sts).name, "sts");
  EXPECT_EQ(table(TableId::Sms1).name, "sms1");
  EXPECT_EQ(table(TableId::D55d).name, "d55d");
  EXPECT_EQ(table(TableId::Smsmb).name, "smsmb");
  EXPECT_EQ(table_from_name("d55d"), TableId::D55d);
  EXPECT_EQ(table_from_name("smsmb"), TableId::Smsmb);
  EXPECT_EQ(table_from_name("STS"), std::nullopt);
  EXPECT_EQ(table(TableId::Smsmb).protocol, protocol::BusProtocol::ModbusRtu);
  EXPECT_EQ(table(TableId::Smsmb).addressing, Addressing::Register);
  EXPECT_EQ(table(TableId::Smsmb).default_byte_order, ByteOrder::HighFirst);
  EXPECT_EQ(table(TableId::Sms1).default_byte_order, ByteOrder::LowFirst);
  EXPECT_TRUE(table(TableId::Sts).has_sync_read);
  EXPECT_FALSE(table(TableId::D55d).has_sync_read);
}

TEST(Tables, EndAddressIsOnePastTheLastFieldsLastAddress) {
  EXPECT_EQ(end_address(table(TableId::Sts)), 71);       // present_current 69-70
  EXPECT_EQ(end_address(table(TableId::Sms1)), 71);      // present_current 69-70
  EXPECT_EQ(end_address(table(TableId::D55d)), 50);      // 49 move without photo-coupler
  EXPECT_EQ(end_address(table(TableId::Smsmb)), 0x197);  // 0x196 speed default
}

TEST(Tables, FieldAtFindsFirstAddressesOnly) {
  const TableSpec& sts = table(TableId::Sts);
  ASSERT_NE(field_at(sts, 42), nullptr);
  EXPECT_EQ(field_at(sts, 42)->name, "goal_position");
  EXPECT_EQ(field_at(sts, 43), nullptr);  // second byte
  EXPECT_EQ(field_at(sts, 53), nullptr);  // gap
  EXPECT_EQ(field_at(sts, 71), nullptr);  // beyond
  EXPECT_EQ(field_at(sts, 0)->name, "firmware_major");
}

TEST(Tables, FieldCoveringFindsBothBytesOfATwoByteField) {
  const TableSpec& sts = table(TableId::Sts);
  EXPECT_EQ(field_covering(sts, 42)->name, "goal_position");
  EXPECT_EQ(field_covering(sts, 43)->name, "goal_position");
  EXPECT_EQ(field_covering(sts, 70)->name, "present_current");
  EXPECT_EQ(field_covering(sts, 50), nullptr);
  EXPECT_EQ(field_covering(sts, 71), nullptr);
  EXPECT_EQ(field_covering(sts, 53), nullptr);  // a gap
  EXPECT_EQ(field_covering(sts, 2)->name, "byte_order_flag");
  // A register table: one address per field.
  const TableSpec& smsmb = table(TableId::Smsmb);
  EXPECT_EQ(field_covering(smsmb, 0x80)->name, "goal_position");
  EXPECT_EQ(field_covering(smsmb, 0x81)->name, "torque_switch");
  EXPECT_EQ(field_covering(smsmb, 0x04), nullptr);
}

TEST(Tables, StsHasTheSpeedGainsSpecOmits) {
  const TableSpec& sts = table(TableId::Sts);
  const FieldSpec* speed_p = field_at(sts, 37);
  const FieldSpec* speed_i = field_at(sts, 39);
  ASSERT_NE(speed_p, nullptr);
  ASSERT_NE(speed_i, nullptr);
  EXPECT_EQ(speed_p->name, "speed_p_gain");
  EXPECT_EQ(speed_i->name, "speed_i_gain");
  EXPECT_EQ(speed_p->size, 1);
  EXPECT_EQ(speed_p->access, Access::ReadWrite);
  EXPECT_EQ(speed_p->area, Area::Eeprom);
}

TEST(Tables, BooleanFieldsSitInTheirBitSpaces) {
  const auto space = [](TableId id, std::uint16_t addr) { return field_at(table(id), addr)->bit_space; };
  EXPECT_EQ(space(TableId::Sts, 40), BitSpace::Coil);
  EXPECT_EQ(space(TableId::Sts, 55), BitSpace::Coil);
  EXPECT_EQ(space(TableId::Sts, 66), BitSpace::DiscreteInput);
  EXPECT_EQ(space(TableId::Sms1, 40), BitSpace::Coil);
  EXPECT_EQ(space(TableId::Sms1, 48), BitSpace::Coil);
  EXPECT_EQ(space(TableId::Sms1, 66), BitSpace::DiscreteInput);
  EXPECT_EQ(space(TableId::D55d, 42), BitSpace::DiscreteInput);
  EXPECT_EQ(space(TableId::D55d, 43), BitSpace::Coil);
  EXPECT_EQ(space(TableId::D55d, 44), BitSpace::DiscreteInput);
  EXPECT_EQ(space(TableId::D55d, 47), BitSpace::Coil);
  EXPECT_EQ(space(TableId::Sts, 42), BitSpace::None);
}

TEST(Tables, FactoryAreaOfSmsmbIsNamed) {
  const TableSpec& smsmb = table(TableId::Smsmb);
  for (std::uint16_t reg = 0x180; reg <= 0x196; ++reg) {
    EXPECT_NE(field_at(smsmb, reg), nullptr) << "register " << reg;
  }
  EXPECT_EQ(field_at(smsmb, 0x193)->name, "angle_resolution");
  EXPECT_EQ(field_at(smsmb, 0x194)->name, "torque_limit_default");
}

TEST(Tables, FieldByNameUsesTheSnakeCaseNames) {
  EXPECT_EQ(field_by_name(table(TableId::Sms1), "position_correction")->addr, 33);
  EXPECT_EQ(field_by_name(table(TableId::D55d), "photo_switch_homing")->addr, 24);
  EXPECT_EQ(field_by_name(table(TableId::Smsmb), "fault_reset")->addr, 0x86);
  EXPECT_EQ(field_by_name(table(TableId::Sts), "no_such_field"), nullptr);
}

// --- encodings (docs/PROTOCOL.md §4) ---------------------------------------------------------------------------

const FieldSpec& sts_field(std::uint16_t addr) { return *field_at(table(TableId::Sts), addr); }

TEST(SignMagnitude, Bit15MinusThousandIs83E8) {
  const FieldSpec& goal_speed = sts_field(46);
  EXPECT_EQ(encode_value(goal_speed, -1000), 0x83E8u);
  EXPECT_EQ(encode_value(goal_speed, 1000), 0x03E8u);
  EXPECT_EQ(decode_value(goal_speed, 0x83E8), -1000);
  EXPECT_EQ(decode_value(goal_speed, 0x03E8), 1000);
  EXPECT_EQ(decode_value(goal_speed, 0x8000), 0);  // "minus zero"
  EXPECT_EQ(encode_value(goal_speed, -32767), 0xFFFFu);
}

TEST(SignMagnitude, Bit11RefusesFiveThousand) {
  const FieldSpec& offset = sts_field(31);
  EXPECT_EQ(encode_value(offset, 5000), std::nullopt);
  EXPECT_EQ(encode_value(offset, -2048), std::nullopt);
  EXPECT_EQ(encode_value(offset, -2047), 0x0FFFu);
  EXPECT_EQ(encode_value(offset, -100), 0x0864u);
  EXPECT_EQ(decode_value(offset, 0x0864), -100);
  EXPECT_EQ(decode_value(offset, 0x07FF), 2047);
}

TEST(SignMagnitude, Bit10LoadAndBit7Temperature) {
  EXPECT_EQ(decode_value(sts_field(60), 0x052C), -300);
  EXPECT_EQ(decode_value(sts_field(60), 0x012C), 300);
  const FieldSpec& temperature = *field_at(table(TableId::D55d), 46);
  EXPECT_EQ(decode_value(temperature, 0x85), -5);
  EXPECT_EQ(decode_value(temperature, 0x50), 80);
  EXPECT_EQ(encode_value(*field_at(table(TableId::D55d), 11), -5), 0x85u);
}

TEST(SignMagnitude, GoalPositionStopsAtMultiTurnLimit) {
  const FieldSpec& goal = sts_field(42);
  EXPECT_EQ(encode_value(goal, 30719), 0x77FFu);
  EXPECT_EQ(encode_value(goal, -30719), 0xF7FFu);
  EXPECT_EQ(encode_value(goal, 30720), std::nullopt);
}

TEST(TwosComplement, SignExtendsOverTheFieldSize) {
  const FieldSpec& speed = *field_at(table(TableId::D55d), 38);
  EXPECT_EQ(decode_value(speed, 0xFC18), -1000);
  EXPECT_EQ(decode_value(speed, 0x8000), -32768);
  EXPECT_EQ(decode_value(speed, 0x7FFF), 32767);
  EXPECT_EQ(encode_value(speed, -1000), 0xFC18u);
  EXPECT_EQ(encode_value(speed, -32768), 0x8000u);
  const FieldSpec& calibration = *field_at(table(TableId::Smsmb), 0x0F);
  EXPECT_EQ(encode_value(calibration, -2047), 0xF801u);
  EXPECT_EQ(encode_value(calibration, -2048), std::nullopt);  // the field's range
}

TEST(Unsigned, OneByteFieldsStopAt254AndRefuseNegatives) {
  const FieldSpec& max_input_voltage = sts_field(14);
  EXPECT_EQ(encode_value(max_input_voltage, 254), 254u);
  EXPECT_EQ(encode_value(max_input_voltage, 255), std::nullopt);
  EXPECT_EQ(encode_value(max_input_voltage, 300), std::nullopt);
  EXPECT_EQ(encode_value(max_input_voltage, -1), std::nullopt);
  EXPECT_EQ(decode_value(max_input_voltage, 0x1FF), 255);  // only the field's byte counts
  // Where Feetech documents a narrower range it wins: max temperature 0-100 (wiki memory-sts).
  EXPECT_EQ(encode_value(sts_field(13), 101), std::nullopt);
}

TEST(AllowedValues, TorqueEnableTakesZeroOneDampingAndCalibrationOnly) {
  const FieldSpec& torque = sts_field(40);
  EXPECT_EQ(encode_value(torque, 0), 0u);
  EXPECT_EQ(encode_value(torque, 1), 1u);
  EXPECT_EQ(encode_value(torque, 2), 2u);  // damping (wiki memory-sts)
  EXPECT_EQ(encode_value(torque, 128), 0x80u);
  EXPECT_EQ(encode_value(torque, 3), std::nullopt);
  EXPECT_EQ(encode_value(torque, 127), std::nullopt);
  EXPECT_EQ(encode_value(torque, 129), std::nullopt);
}

TEST(RawBytes, LoadAndStoreInBothByteOrders) {
  const std::vector<std::uint8_t> bytes{0xE8, 0x83};
  EXPECT_EQ(load_raw(bytes, 2, ByteOrder::LowFirst), 0x83E8u);
  EXPECT_EQ(load_raw(bytes, 2, ByteOrder::HighFirst), 0xE883u);
  EXPECT_EQ(load_raw(bytes, 1, ByteOrder::HighFirst), 0xE8u);
  std::vector<std::uint8_t> out(2, 0);
  store_raw(out, 2, ByteOrder::LowFirst, 0x0518);
  EXPECT_EQ(out, (std::vector<std::uint8_t>{0x18, 0x05}));
  store_raw(out, 2, ByteOrder::HighFirst, 0x0518);
  EXPECT_EQ(out, (std::vector<std::uint8_t>{0x05, 0x18}));
  store_raw(out, 1, ByteOrder::HighFirst, 0x7F);
  EXPECT_EQ(out, (std::vector<std::uint8_t>{0x7F, 0x18}));
}

TEST(RawBytes, RefuseToReadOrWritePastTheSpan) {
  const std::vector<std::uint8_t> one{0x01};
  EXPECT_THROW(load_raw(one, 2, ByteOrder::LowFirst), std::out_of_range);
  std::vector<std::uint8_t> out(1, 0);
  EXPECT_THROW(store_raw(out, 2, ByteOrder::LowFirst, 0x1234), std::out_of_range);
  EXPECT_EQ(out[0], 0x00);
}

}  // namespace
}  // namespace sms::modbus_map
