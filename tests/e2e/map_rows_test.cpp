// Every row of docs/PLC_GUIDE.md "A servo unit", on each table (sts, sms1, d55d) and both
// profiles (native, smsmb), through real processes: libmodbus -> sms-gateway -> pty -> sms-sim.
// What a write did is checked in the simulator's own memory (its control socket).
#include <gtest/gtest.h>

#include "tests/e2e/plant.h"
#include "tests/support/eventually.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

// Addresses and values of one unit, read off docs/PROTOCOL.md §2 and docs/PLC_GUIDE.md by hand.
struct UnitRow {
  const char* label;
  int unit;
  int servo_id;
  // A two-byte writable field: Modbus address, the simulator's field name, a value to write.
  int goal;
  const char* goal_field;
  int goal_value;
  int second_byte;  // the field's second address (byte tables), -1 on register tables
  // A signed writable field (two's complement on Modbus).
  int signed_reg;
  const char* signed_field;
  int signed_value;
  int small_reg;  // a field with a small range, and a value beyond it (0x03)
  int too_big;
  int read_only;  // a read-only field (write: 0x02)
  int beyond;     // past the table (0x02)
  int feedback;   // an input register served from the poll cache, and its field
  const char* feedback_field;
  int coil;  // a boolean RW field shown as a coil
  const char* coil_field;
  int discrete;  // a boolean R field shown as a discrete input
  const char* discrete_field;
  // 1003: the identity read at discovery, from the simulator's fields.
  long (*identity)(SimProcess&, int id);
};

// The model word at 3-4, low byte (3) first, as Feetech's SDKs read it (docs/DECISIONS.md).
long sts_model(SimProcess& sim, int id) { return (sim.field(id, "model_minor") << 8) | sim.field(id, "model_major"); }
long sms1_version(SimProcess& sim, int id) { return sim.field(id, "software_version"); }
long d55d_vendor(SimProcess& sim, int id) { return sim.field(id, "vendor_code"); }

const UnitRow kRows[] = {
    {"sts_native",
     1,
     1,
     42,
     "goal_position",
     1500,
     43,
     46,
     "goal_speed",
     -700,
     41,
     300,
     56,
     200,
     56,
     "present_position",
     40,
     "torque_enable",
     66,
     "moving",
     sts_model},
    {"sts_smsmb",
     3,
     3,
     0x80,
     "goal_position",
     1500,
     -1,
     0x0F,
     "position_offset",
     -300,
     0x81,
     2,
     0x101,
     0x1F0,
     0x104,
     "present_voltage",
     0x81,
     "torque_enable",
     0x106,
     "moving",
     sts_model},
    {"sms1_native",
     4,
     4,
     42,
     "goal_position",
     1500,
     43,
     46,
     "run_speed",
     -700,
     7,
     300,
     56,
     200,
     56,
     "present_position",
     40,
     "torque_switch",
     66,
     "moving",
     sms1_version},
    {"sms1_smsmb",
     5,
     5,
     0x80,
     "goal_position",
     1500,
     -1,
     0x0F,
     "position_correction",
     -300,
     0x81,
     2,
     0x101,
     0x1F0,
     0x104,
     "present_voltage",
     0x81,
     "torque_switch",
     0x106,
     "moving",
     sms1_version},
    {"d55d_native", 11, 1,   30, "goal_position",    90, 31,      32, "run_speed", -300,       34,
     300,           36, 200, 36, "present_position", 43, "brake", 42, "moving",    d55d_vendor},
};

// Test logs name the row, not its bytes.
void PrintTo(const UnitRow& row, std::ostream* out) { *out << row.label; }

class MapRows : public ::testing::TestWithParam<UnitRow> {
 protected:
  static void SetUpTestSuite() { plant_ = std::make_unique<Plant>(); }
  static void TearDownTestSuite() { plant_.reset(); }

  void SetUp() override { wait_until_polled(plant_->port(), row().unit); }

  const UnitRow& row() const { return GetParam(); }
  SimProcess& sim() { return plant_->sim_of(row().unit); }
  long field(const char* name) { return sim().field(row().servo_id, name); }
  ModbusClient client() { return ModbusClient(plant_->port(), row().unit); }
  static std::uint16_t reg(int value) { return static_cast<std::uint16_t>(value); }

  static std::unique_ptr<Plant> plant_;
};
std::unique_ptr<Plant> MapRows::plant_;

TEST_P(MapRows, HoldingRegisterWriteReachesTheServoAndReadsBackLive) {
  auto c = client();
  ASSERT_TRUE(c.write_register(row().goal, reg(row().goal_value)).ok());
  EXPECT_EQ(field(row().goal_field), row().goal_value);
  EXPECT_EQ(c.read_holding(row().goal, 1).values, std::vector<std::uint16_t>{reg(row().goal_value)});
}

TEST_P(MapRows, WriteMultipleIgnoresTheSecondAddressOfAField) {
  auto c = client();
  if (row().second_byte < 0) {  // register tables: FC16 over two real registers
    ASSERT_TRUE(c.write_registers(row().goal, {reg(row().goal_value - 10), 1}).ok());
    EXPECT_EQ(field(row().goal_field), row().goal_value - 10);
    EXPECT_EQ(field(row().coil_field), 1);
    return;
  }
  ASSERT_TRUE(c.write_registers(row().goal, {reg(row().goal_value - 10), 0x1234}).ok());
  EXPECT_EQ(field(row().goal_field), row().goal_value - 10);
  EXPECT_EQ(c.read_holding(row().goal, 2).values, (std::vector<std::uint16_t>{reg(row().goal_value - 10), 0}));
  // A write touching only the second address: no field there.
  EXPECT_EQ(c.write_register(row().second_byte, 7).exception, 0x02);
  EXPECT_EQ(field(row().goal_field), row().goal_value - 10);
}

TEST_P(MapRows, ReadWriteMultipleWritesFirstThenReads) {
  auto c = client();
  const auto answer = c.write_and_read(row().goal, {reg(row().goal_value + 20)}, row().goal, 1);
  ASSERT_TRUE(answer.ok()) << answer.error;
  EXPECT_EQ(answer.values, std::vector<std::uint16_t>{reg(row().goal_value + 20)});
  EXPECT_EQ(field(row().goal_field), row().goal_value + 20);
}

TEST_P(MapRows, SignedFieldsAreTwosComplement) {
  auto c = client();
  ASSERT_TRUE(c.write_register(row().signed_reg, reg(row().signed_value)).ok());
  EXPECT_EQ(field(row().signed_field), row().signed_value);
  EXPECT_EQ(c.read_holding(row().signed_reg, 1).values, std::vector<std::uint16_t>{reg(row().signed_value)});
  ASSERT_TRUE(c.write_register(row().signed_reg, 0).ok());
}

TEST_P(MapRows, AddressAndValueExceptions) {
  auto c = client();
  EXPECT_EQ(c.write_register(row().small_reg, reg(row().too_big)).exception, 0x03);
  EXPECT_EQ(c.write_register(row().read_only, 1).exception, 0x02);
  EXPECT_EQ(c.read_holding(row().beyond, 1).exception, 0x02);
  EXPECT_EQ(c.read_input(row().beyond, 1).exception, 0x02);
  EXPECT_EQ(c.read_coils(row().goal, 1).exception, 0x02);  // not a boolean field
  EXPECT_EQ(c.read_discrete(row().goal, 1).exception, 0x02);
}

TEST_P(MapRows, InputRegistersServeThePolledValues) {
  auto c = client();
  EXPECT_TRUE(eventually([&] {
    const auto answer = c.read_input(row().feedback, 1);
    return answer.ok() && answer.values[0] == reg(static_cast<int>(field(row().feedback_field)));
  }));
}

TEST_P(MapRows, FactRegistersAndBits) {
  auto c = client();
  const auto facts = c.read_input(1000, 8);
  ASSERT_TRUE(facts.ok()) << facts.error;
  EXPECT_EQ(facts.values[1], 1);  // online
  EXPECT_LT(facts.values[2], 2000);
  EXPECT_EQ(facts.values[3], row().identity(sim(), row().servo_id));
  EXPECT_GT((facts.values[4] << 16) | facts.values[5], 0);
  const auto online = c.read_discrete(1008, 1);
  ASSERT_TRUE(online.ok()) << online.error;
  EXPECT_EQ(online.values, std::vector<std::uint8_t>{1});
  const auto status_bits = c.read_discrete(1000, 8);
  ASSERT_TRUE(status_bits.ok()) << status_bits.error;
  for (int b = 0; b < 8; ++b) EXPECT_EQ(status_bits.values[b], (facts.values[0] >> b) & 1) << "bit " << b;
}

TEST_P(MapRows, StagedWriteRunsOnTheActionCoil) {
  auto c = client();
  ASSERT_TRUE(c.write_register(row().goal, reg(row().goal_value)).ok());
  ASSERT_TRUE(c.write_register(512 + row().goal, reg(row().goal_value + 5)).ok());
  EXPECT_EQ(field(row().goal_field), row().goal_value);  // held by the servo
  ModbusClient gateway(plant_->port(), 255);
  ASSERT_TRUE(gateway.write_coil(0, true).ok());
  EXPECT_TRUE(eventually([&] { return field(row().goal_field) == row().goal_value + 5; }));
}

TEST_P(MapRows, CoilsAreTheBooleanFields) {
  auto c = client();
  ASSERT_TRUE(c.write_coil(row().coil, false).ok());
  EXPECT_EQ(field(row().coil_field), 0);
  EXPECT_EQ(c.read_coils(row().coil, 1).values, std::vector<std::uint8_t>{0});
  ASSERT_TRUE(c.write_coils(row().coil, {1}).ok());
  EXPECT_EQ(field(row().coil_field), 1);
  EXPECT_EQ(c.read_coils(row().coil, 1).values, std::vector<std::uint8_t>{1});
}

TEST_P(MapRows, DiscreteInputsAreTheBooleanReadOnlyFields) {
  auto c = client();
  EXPECT_TRUE(eventually([&] {
    const auto answer = c.read_discrete(row().discrete, 1);
    return answer.ok() && answer.values[0] == (field(row().discrete_field) != 0 ? 1 : 0);
  }));
}

INSTANTIATE_TEST_SUITE_P(EveryTableAndProfile, MapRows, ::testing::ValuesIn(kRows),
                         [](const ::testing::TestParamInfo<UnitRow>& info) { return std::string(info.param.label); });

// d55d shows its REG WRITE flag (address 44) as a discrete input: set by a staged write,
// cleared by ACTION.
TEST(MapRowsD55d, RegWritePendingFlagFollowsStagedWriteAndAction) {
  Plant plant;
  wait_until_polled(plant.port(), 12);
  ModbusClient unit(plant.port(), 12);
  ASSERT_TRUE(unit.write_register(512 + 30, 45).ok());
  EXPECT_EQ(plant.base().field(2, "reg_write_flag"), 1);
  EXPECT_TRUE(eventually([&] { return unit.read_discrete(44, 1).values == std::vector<std::uint8_t>{1}; }));
  ModbusClient gateway(plant.port(), 255);
  ASSERT_TRUE(gateway.write_coil(0, true).ok());
  EXPECT_TRUE(eventually([&] { return plant.base().field(2, "goal_position") == 45; }));
  EXPECT_TRUE(eventually([&] { return unit.read_discrete(44, 1).values == std::vector<std::uint8_t>{0}; }));
}

}  // namespace
}  // namespace sms::e2e
