// The text forms sms-sim and the control socket accept.
#include "simulator/bus_spec.h"

#include <gtest/gtest.h>

namespace sms::simulator {
namespace {

using modbus_map::TableId;
using protocol::BusProtocol;

TEST(BusSpec, IdListAcceptsRangesAndCommas) {
  EXPECT_EQ(*parse_id_list("1-6"), (std::vector<std::uint8_t>{1, 2, 3, 4, 5, 6}));
  EXPECT_EQ(*parse_id_list("1,3,7"), (std::vector<std::uint8_t>{1, 3, 7}));
  EXPECT_EQ(*parse_id_list("1-3,9"), (std::vector<std::uint8_t>{1, 2, 3, 9}));
  EXPECT_EQ(*parse_id_list("0x10"), (std::vector<std::uint8_t>{16}));
}

TEST(BusSpec, IdListRejectsWhatIsNotAnId) {
  EXPECT_FALSE(parse_id_list("6-1"));
  EXPECT_FALSE(parse_id_list("1,,2"));
  EXPECT_FALSE(parse_id_list("254"));
  EXPECT_FALSE(parse_id_list("a"));
  const auto error = parse_id_list("1-x");
  ASSERT_FALSE(error);
  EXPECT_NE(error.error().find("1-6 or 1,3,7"), std::string::npos) << error.error();
}

TEST(BusSpec, ServoSpecFillsProtocolAndBaudFromTheTable) {
  EXPECT_EQ(*parse_servo_spec("3:sts:feetech:500000"), (ServoConfig{3, TableId::Sts, BusProtocol::Feetech, 500'000}));
  EXPECT_EQ(*parse_servo_spec("4:smsmb"), (ServoConfig{4, TableId::Smsmb, BusProtocol::ModbusRtu, 115'200}));
  EXPECT_EQ(*parse_servo_spec("5:d55d::9600"), (ServoConfig{5, TableId::D55d, BusProtocol::D55d, 9'600}));
  EXPECT_EQ(*parse_servo_spec("6:sms1"), (ServoConfig{6, TableId::Sms1, BusProtocol::Feetech, 1'000'000}));
}

TEST(BusSpec, ServoSpecRejectsATableOnTheWrongProtocol) {
  const auto error = parse_servo_spec("3:sts:d55d:115200");
  ASSERT_FALSE(error);
  EXPECT_NE(error.error().find("spoken over feetech"), std::string::npos) << error.error();
  EXPECT_FALSE(parse_servo_spec("3:stx"));
  EXPECT_FALSE(parse_servo_spec("3"));
  EXPECT_FALSE(parse_servo_spec("3:sts:feetech:fast"));
}

TEST(BusSpec, IdValuePairs) {
  EXPECT_EQ(*parse_id_value("2:50"), (std::pair<std::uint8_t, std::uint32_t>{2, 50}));
  EXPECT_EQ(*parse_id_value("2:0x24"), (std::pair<std::uint8_t, std::uint32_t>{2, 0x24}));
  EXPECT_FALSE(parse_id_value("2"));
  EXPECT_FALSE(parse_id_value("2:-1"));
}

TEST(BusSpec, NumbersAndProbabilities) {
  EXPECT_EQ(parse_number("42"), 42U);
  EXPECT_EQ(parse_number("0x2A"), 42U);
  EXPECT_FALSE(parse_number("42x"));
  EXPECT_FALSE(parse_number(""));
  EXPECT_EQ(parse_probability("0.25"), 0.25);
  EXPECT_FALSE(parse_probability("1.5"));
  EXPECT_FALSE(parse_probability("-0.1"));
}

}  // namespace
}  // namespace sms::simulator
