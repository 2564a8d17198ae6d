// Input registers 1000-1007 of a servo unit from the gateway's facts (docs/PLC_GUIDE.md "A servo
// unit"): values written out by hand.
#include <gtest/gtest.h>

#include "gateway/units/unit_router.h"

namespace sms::gateway {
namespace {

using Registers = std::array<std::uint16_t, servo_facts_layout::kRegisterCount>;

TEST(ServoFactRegisters, LayoutOfTheEightRegisters) {
  ServoFacts facts;
  facts.last_status = 0x24;
  facts.online = true;
  facts.cache_age = std::chrono::milliseconds{37};
  facts.identity = 0x082A;
  facts.replies_ok = 0x0001'2345;
  facts.timeouts = 7;
  EXPECT_EQ(servo_fact_registers(facts), (Registers{0x0024, 1, 37, 0x082A, 0x0001, 0x2345, 0x0000, 0x0007}));
}

TEST(ServoFactRegisters, CacheAgeSaturatesAndNeverPolledReads65535) {
  ServoFacts facts;
  facts.cache_age = std::chrono::milliseconds{70'000};
  EXPECT_EQ(servo_fact_registers(facts)[2], 65535);
  facts.cache_age = std::chrono::milliseconds{65'535};
  EXPECT_EQ(servo_fact_registers(facts)[2], 65535);
  facts.cache_age = std::chrono::milliseconds{65'534};
  EXPECT_EQ(servo_fact_registers(facts)[2], 65534);
  facts.cache_age.reset();
  EXPECT_EQ(servo_fact_registers(facts)[2], 65535);
  EXPECT_EQ(servo_fact_registers(facts)[1], 0);  // offline
}

TEST(ServoFactRegisters, CountersAre32BitHighWordFirstAndWrap) {
  ServoFacts facts;
  facts.replies_ok = 0x1'FFFF'FFFFull;  // past 32 bits: the low 32 show, as a wrapping counter
  facts.timeouts = 0x0002'0000;
  const Registers registers = servo_fact_registers(facts);
  EXPECT_EQ(registers[4], 0xFFFF);
  EXPECT_EQ(registers[5], 0xFFFF);
  EXPECT_EQ(registers[6], 0x0002);
  EXPECT_EQ(registers[7], 0x0000);
}

TEST(WritesAnswered, ResponseLevelsPerTable) {
  using modbus_map::TableId;
  EXPECT_FALSE(writes_answered(TableId::Sts, 0));  // only READ and PING answered
  EXPECT_TRUE(writes_answered(TableId::Sts, 1));
  EXPECT_FALSE(writes_answered(TableId::Sms1, 0));
  EXPECT_TRUE(writes_answered(TableId::Sms1, 1));
  EXPECT_FALSE(writes_answered(TableId::D55d, 0));  // never
  EXPECT_FALSE(writes_answered(TableId::D55d, 1));  // READ only
  EXPECT_TRUE(writes_answered(TableId::D55d, 2));   // all but broadcast
  EXPECT_TRUE(writes_answered(TableId::Smsmb, 0));  // Modbus slaves always answer
}

}  // namespace
}  // namespace sms::gateway
