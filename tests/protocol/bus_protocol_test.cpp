#include "protocol/bus_protocol.h"

#include <gtest/gtest.h>

namespace sms::protocol {
namespace {

TEST(BusProtocol, SpellsEachProtocolAsConfigsDo) {
  EXPECT_EQ(to_string(BusProtocol::Feetech), "feetech");
  EXPECT_EQ(to_string(BusProtocol::D55d), "d55d");
  EXPECT_EQ(to_string(BusProtocol::ModbusRtu), "modbus-rtu");
}

TEST(BusProtocol, ParsesOnlyTheExactSpelling) {
  EXPECT_EQ(bus_protocol_from_string("feetech"), BusProtocol::Feetech);
  EXPECT_EQ(bus_protocol_from_string("d55d"), BusProtocol::D55d);
  EXPECT_EQ(bus_protocol_from_string("modbus-rtu"), BusProtocol::ModbusRtu);
  EXPECT_EQ(bus_protocol_from_string("modbus_rtu"), std::nullopt);
  EXPECT_EQ(bus_protocol_from_string("Feetech"), std::nullopt);
  EXPECT_EQ(bus_protocol_from_string(""), std::nullopt);
}

}  // namespace
}  // namespace sms::protocol
