// The one value check of a client's write (RegisterMap::check_write): access, range, allowed
// values and the smsmb profile's links, with the same exception and message as a Modbus write
// of the same value (plan_register_write runs it), the register value to send, and the servo's
// field it lands in (whose area says whether it is EEPROM). The console and the Sparkplug node
// call it before they build a request (tests/gateway/console/console_write_test.cpp).
#include <gtest/gtest.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "modbus_map/register_map.h"

namespace sms::modbus_map {
namespace {

RegisterMap make(TableId id, Profile profile = Profile::Native) {
  auto map = RegisterMap::create(id, profile);
  if (!map) throw std::runtime_error(map.error());
  return std::move(map).value();
}

const RegisterEntry& entry(const RegisterMap& map, std::uint16_t address) {
  const RegisterEntry* found = map.entry_at(address);
  if (found == nullptr) throw std::invalid_argument("no entry at " + std::to_string(address));
  return *found;
}

// check_write's refusal, and that a Modbus FC06 of the same value is refused the same way.
MapError refused(const RegisterMap& map, std::uint16_t address, std::int64_t value) {
  const auto checked = map.check_write(entry(map, address), value);
  if (checked) throw std::logic_error("value " + std::to_string(value) + " was taken");
  if (value >= -32768 && value <= 65535) {
    const std::vector<std::uint16_t> registers{static_cast<std::uint16_t>(value)};
    const auto plan = map.plan_register_write(address, registers);
    EXPECT_FALSE(plan);
    if (!plan) {
      EXPECT_EQ(plan.error().code, checked.error().code);
      EXPECT_EQ(plan.error().message, checked.error().message);
    }
  }
  return checked.error();
}

TEST(ValueCheck, ARangeRefusalIs03AndSaysTheRange) {
  const RegisterMap sts = make(TableId::Sts);
  const MapError error = refused(sts, 42, 31000);
  EXPECT_EQ(error.code, ModbusException::IllegalDataValue);
  EXPECT_EQ(error.message, "value 31000 for goal_position (42) of table sts is outside -30719..30719");
  EXPECT_EQ(to_string(error),
            "exception 0x03 (illegal data value): value 31000 for goal_position (42) of table sts is outside "
            "-30719..30719");
  // A value no register holds is refused by its range, not wrapped into one.
  EXPECT_EQ(sts.check_write(entry(sts, 42), 70000).error().message,
            "value 70000 for goal_position (42) of table sts is outside -30719..30719");
}

TEST(ValueCheck, AValueNotAllowedIs03AndListsTheAllowedOnes) {
  const RegisterMap sts = make(TableId::Sts);
  const MapError error = refused(sts, 40, 3);  // torque_enable: 0, 1, 2 (damping), 128
  EXPECT_EQ(error.code, ModbusException::IllegalDataValue);
  EXPECT_NE(error.message.find("not one of 0 1 2 128"), std::string::npos) << error.message;
  // Through the smsmb profile's value map: the accepted register values.
  const RegisterMap profile = make(TableId::Sts, Profile::Smsmb);
  EXPECT_NE(refused(profile, 0x10, 3).message.find("accepted: 0, 1, 4"), std::string::npos);
}

TEST(ValueCheck, AReadOnlyFieldOrOneWithoutCounterpartIs02) {
  const RegisterMap sts = make(TableId::Sts);
  const MapError error = refused(sts, 56, 5);
  EXPECT_EQ(error.code, ModbusException::IllegalDataAddress);
  EXPECT_EQ(error.message, "present_position (56) of table sts is read-only");
  const MapError missing = refused(make(TableId::Sms1, Profile::Smsmb), 0x14, 1);
  EXPECT_EQ(missing.code, ModbusException::IllegalDataAddress);
  EXPECT_NE(missing.message.find("no counterpart"), std::string::npos) << missing.message;
}

TEST(ValueCheck, ATakenValueIsTheRegisterToSendAndNamesTheServoFieldAndItsArea) {
  const RegisterMap sts = make(TableId::Sts);
  const auto goal = sts.check_write(entry(sts, 42), -1000);
  ASSERT_TRUE(goal) << goal.error().message;
  EXPECT_EQ(goal->register_value, 0xFC18);  // two's complement, as a Modbus client sends it
  ASSERT_NE(goal->servo_field, nullptr);
  EXPECT_EQ(goal->servo_field->area, Area::Ram);
  // The EEPROM rule's input: an EEPROM field persists only with the lock open (eeprom_lock.h) and
  // needs role engineer (the role policy).
  const auto limit = sts.check_write(entry(sts, 13), 70);
  ASSERT_TRUE(limit) << limit.error().message;
  EXPECT_EQ(limit->servo_field->name, "max_temperature");
  EXPECT_EQ(limit->servo_field->area, Area::Eeprom);
  // The smsmb profile: the servo's own field behind the SMSMB register.
  const RegisterMap profile = make(TableId::Sts, Profile::Smsmb);
  const auto id = profile.check_write(entry(profile, 0x0A), 7);
  ASSERT_TRUE(id) << id.error().message;
  EXPECT_EQ(id->servo_field->name, "id");
  EXPECT_EQ(id->servo_field->area, Area::Eeprom);
}

}  // namespace
}  // namespace sms::modbus_map
