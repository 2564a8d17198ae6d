#include "modbus_map/baud_tables.h"

#include <gtest/gtest.h>

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;

TEST(FeetechBauds, MapBothWays) {
  EXPECT_EQ(baud_from_code(BusProtocol::Feetech, 0), 1'000'000u);
  EXPECT_EQ(baud_from_code(BusProtocol::Feetech, 4), 115'200u);
  EXPECT_EQ(baud_from_code(BusProtocol::Feetech, 5), 76'800u);
  EXPECT_EQ(baud_from_code(BusProtocol::Feetech, 11), 4'800u);
  EXPECT_EQ(baud_from_code(BusProtocol::Feetech, 12), std::nullopt);
  EXPECT_EQ(*baud_code(BusProtocol::Feetech, 1'000'000), 0);
  EXPECT_EQ(*baud_code(BusProtocol::Feetech, 38'400), 7);
  EXPECT_EQ(*baud_code(BusProtocol::Feetech, 19'200), 8);
  EXPECT_EQ(baud_table(BusProtocol::Feetech).size(), 12u);
}

TEST(ModbusRtuBauds, MapBothWays) {
  EXPECT_EQ(baud_from_code(BusProtocol::ModbusRtu, 0), 256'000u);
  EXPECT_EQ(baud_from_code(BusProtocol::ModbusRtu, 2), 115'200u);
  EXPECT_EQ(baud_from_code(BusProtocol::ModbusRtu, 4), 56'000u);
  EXPECT_EQ(baud_from_code(BusProtocol::ModbusRtu, 9), 4'800u);
  EXPECT_EQ(baud_from_code(BusProtocol::ModbusRtu, 10), std::nullopt);
  EXPECT_EQ(*baud_code(BusProtocol::ModbusRtu, 9'600), 8);
  EXPECT_EQ(*baud_code(BusProtocol::ModbusRtu, 57'600), 3);
}

TEST(D55dBauds, CodeZeroDependsOnTheMotorKind) {
  EXPECT_EQ(baud_from_code(BusProtocol::D55d, 0, /*base_motor=*/true), 115'200u);
  EXPECT_EQ(baud_from_code(BusProtocol::D55d, 0, /*base_motor=*/false), 9'600u);
  EXPECT_EQ(baud_from_code(BusProtocol::D55d, 0), 9'600u);
  // The rate never maps back to the ambiguous code 0.
  EXPECT_EQ(*baud_code(BusProtocol::D55d, 115'200), 4);
  EXPECT_EQ(*baud_code(BusProtocol::D55d, 9'600), 2);
  EXPECT_EQ(baud_from_code(BusProtocol::D55d, 10), 1'792'000u);
  EXPECT_EQ(baud_from_code(BusProtocol::D55d, 11), std::nullopt);
  EXPECT_EQ(baud_table(BusProtocol::D55d).front().code, 1);
}

TEST(BaudErrors, NameTheProtocolTheRateAndEveryValidRate) {
  const auto code = baud_code(BusProtocol::ModbusRtu, 1'000'000);
  ASSERT_FALSE(code);
  EXPECT_EQ(code.error(),
            "modbus-rtu bus: 1000000 bps is not in the baud table (docs/PROTOCOL.md §3); valid rates: 256000, 128000, "
            "115200, "
            "57600, 56000, 38400, 19200, 14400, 9600, 4800");
  EXPECT_EQ(valid_bauds_text(BusProtocol::Feetech),
            "1000000, 500000, 250000, 128000, 115200, 76800, 57600, 38400, 19200, 14400, 9600, 4800");
  EXPECT_EQ(valid_bauds_text(BusProtocol::D55d),
            "2400, 9600, 38400, 115200, 256000, 460800, 896000, 921600, 1280000, 1792000");
  EXPECT_FALSE(baud_code(BusProtocol::Feetech, 56'000));
}

}  // namespace
}  // namespace sms::modbus_map
