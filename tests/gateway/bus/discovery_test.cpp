// Identity decoding and the discovery summary text (the engine's discovery itself runs
// against the simulator in poll_cycle_test.cpp).
#include "gateway/bus/discovery.h"

#include <gtest/gtest.h>

#include <array>

#include <vector>

#include "modbus_map/tables.h"

namespace sms::gateway {
namespace {

using modbus_map::ByteOrder;
using modbus_map::TableId;

TEST(Discovery, StsIdentityIsFirmwareMajorMinorAndTheModelWord) {
  const IdentityLayout* layout = identity_layout(TableId::Sts);
  ASSERT_NE(layout, nullptr);
  EXPECT_EQ(layout->read, (AddressBlock{0, 9}));
  // Addresses 0-8: firmware 2.48, byte-order flag 0, model 8 / 42 (one word low byte first:
  // 10760, the SM40BL), ID 1, baud code 0, return delay 250, response level 1.
  const std::vector<std::uint8_t> bytes{0x02, 0x30, 0x00, 0x08, 0x2A, 0x01, 0x00, 0xFA, 0x01};
  const ServoIdentity identity = decode_identity(*layout, bytes, ByteOrder::LowFirst);
  EXPECT_EQ(decode_response_level(*layout, bytes), 1);
  EXPECT_EQ(identity.firmware, 0x0230);
  EXPECT_EQ(identity.model, 10760);
  EXPECT_EQ(format_identity_value(layout, true, identity.model), "10760 (SM40BL)");
  EXPECT_EQ(format_identity_value(layout, true, 4242), "4242");  // a model without a known name
  EXPECT_EQ(format_identity_value(layout, false, identity.firmware), "2.48");
}

TEST(Discovery, ScsModelWordIsHighByteFirst) {
  const IdentityLayout* layout = identity_layout(TableId::Scs);
  ASSERT_NE(layout, nullptr);
  const std::vector<std::uint8_t> bytes{0x01, 0x00, 0x01, 0x05, 0x04, 0x01, 0x00, 0x00, 0x01};
  EXPECT_EQ(decode_identity(*layout, bytes, ByteOrder::HighFirst).model, 1284);
  EXPECT_EQ(format_identity_value(layout, true, 1284), "1284 (SCS0009)");
}

TEST(Discovery, ByteOrderFlagTellsScsFromSts) {
  const std::vector<std::uint8_t> scs{0x01, 0x00, 0x01};
  const std::vector<std::uint8_t> sts{0x02, 0x30, 0x00};
  EXPECT_EQ(table_from_byte_order_flag(TableId::Sts, scs), TableId::Scs);
  EXPECT_EQ(table_from_byte_order_flag(TableId::Scs, sts), TableId::Sts);
  EXPECT_EQ(table_from_byte_order_flag(TableId::Sts, std::vector<std::uint8_t>{0x02, 0x30}), std::nullopt);
  EXPECT_EQ(table_from_byte_order_flag(TableId::Sms1, scs), std::nullopt);  // sms1 has no flag
}

TEST(Discovery, Sms1SoftwareVersionFollowsTheServosByteOrder) {
  const IdentityLayout* layout = identity_layout(TableId::Sms1);
  ASSERT_NE(layout, nullptr);
  EXPECT_EQ(layout->read, (AddressBlock{3, 6}));
  // Addresses 3-8: software version, ID 1, baud code 0, return delay 0, response level 0.
  const std::vector<std::uint8_t> bytes{0x34, 0x12, 0x01, 0x00, 0x00, 0x00};
  EXPECT_EQ(decode_response_level(*layout, bytes), 0);
  EXPECT_EQ(decode_identity(*layout, bytes, ByteOrder::LowFirst).firmware, 0x1234);
  EXPECT_EQ(decode_identity(*layout, bytes, ByteOrder::HighFirst).firmware, 0x3412);
  EXPECT_FALSE(decode_identity(*layout, bytes, ByteOrder::LowFirst).model);
  EXPECT_EQ(format_identity_value(layout, false, 0x0101), "0x0101");
  EXPECT_EQ(format_identity_value(layout, true, std::nullopt), "-");
}

TEST(Discovery, D55dIdentityIsVendorCodeAndSoftwareVersion) {
  const IdentityLayout* layout = identity_layout(TableId::D55d);
  ASSERT_NE(layout, nullptr);
  // Addresses 0-16: vendor code, -, software version, ID 3, baud code 4, return delay 16,
  // CW limit 0, CCW limit 3600, -, max temperature 80, max current 20, resolution 10, -, -,
  // response level 2.
  const std::vector<std::uint8_t> bytes{0x5D, 0x00, 0x01, 0x03, 0x04, 0x10, 0x00, 0x00, 0x10,
                                        0x0E, 0x00, 0x50, 0x14, 0x0A, 0x00, 0x00, 0x02};
  const ServoIdentity identity = decode_identity(*layout, bytes, ByteOrder::LowFirst);
  EXPECT_EQ(decode_response_level(*layout, bytes), 2);
  EXPECT_EQ(identity.model, 0x5D);
  EXPECT_EQ(identity.firmware, 1);
  EXPECT_EQ(format_identity_value(layout, true, identity.model), "93");
}

TEST(Discovery, ShortIdentityReadYieldsNoValues) {
  const IdentityLayout* layout = identity_layout(TableId::Sts);
  const std::vector<std::uint8_t> bytes{0x02, 0x30};
  const ServoIdentity identity = decode_identity(*layout, bytes, ByteOrder::LowFirst);
  EXPECT_EQ(identity.firmware, 0x0230);
  EXPECT_FALSE(identity.model);
  EXPECT_FALSE(decode_response_level(*layout, bytes));
}

TEST(Discovery, ResponseLevelOffsetsPointAtTheTablesResponseLevelField) {
  for (const auto& layout : kIdentityLayouts) {
    const auto* field = modbus_map::field_by_name(modbus_map::table(layout.table), "response_level");
    if (layout.table == TableId::Smsmb) {  // a Modbus slave answers every unicast request
      EXPECT_EQ(field, nullptr);
      EXPECT_FALSE(layout.response_level_offset);
      continue;
    }
    ASSERT_NE(field, nullptr);
    EXPECT_EQ(layout.response_level_address(), field->addr) << modbus_map::table(layout.table).name;
    ASSERT_TRUE(layout.response_level_offset);
    EXPECT_LT(*layout.response_level_offset, layout.read.count);
  }
}

// SMSMB (docs/PROTOCOL.md §2.4): register 0x00 firmware version, 0x01 servo (model) version, high byte first;
// the engine core and the scan read them through this row.
TEST(Discovery, SmsmbIdentityIsRegistersZeroAndOne) {
  const IdentityLayout* layout = identity_layout(TableId::Smsmb);
  ASSERT_NE(layout, nullptr);
  EXPECT_EQ(layout->read, (AddressBlock{0x00, 2}));
  const std::array<std::uint8_t, 4> registers{0x01, 0x03, 0x00, 0x2A};  // firmware 0x0103, model 42
  const ServoIdentity identity = decode_identity(*layout, registers, modbus_map::ByteOrder::HighFirst);
  EXPECT_EQ(identity.firmware, 0x0103);
  EXPECT_EQ(identity.model, 42);
  EXPECT_EQ(format_identity_value(layout, false, identity.firmware), "0x0103");
  EXPECT_FALSE(decode_response_level(*layout, registers));
}

TEST(Discovery, SummaryHasOneLinePerServo) {
  std::vector<DiscoveredServo> servos(2);
  servos[0].servo_id = 1;
  servos[0].online = true;
  servos[0].identity = {10760, 0x0230};
  servos[1].servo_id = 12;
  servos[1].detail = "no answer to PING (3 attempts)";
  const std::string text = format_discovery_summary({"arm", "/dev/ttyUSB0", "feetech", 1'000'000, servos});
  EXPECT_EQ(text,
            "bus arm: /dev/ttyUSB0, feetech at 1000000 bit/s, 1 of 2 servos online\n"
            "  servo   1  sts   online   model 10760 (SM40BL) firmware 2.48   status 0x00\n"
            "  servo  12  sts   OFFLINE  no answer to PING (3 attempts)");
}

}  // namespace
}  // namespace sms::gateway
