#include "modbus_map/eeprom_lock.h"

#include "modbus_map/tables.h"

namespace sms::modbus_map {

const FieldSpec* eeprom_lock(const TableSpec& table) { return field_by_name(table, "lock"); }

std::string EepromUnlock::unlock_text() const {
  const std::string name = field != nullptr ? std::string(field->name) : "lock";
  return "unlocking the EEPROM (" + name + " " + std::to_string(read) + " -> " + std::to_string(kEepromUnlocked) +
         ") so the change survives power-off";
}

std::string EepromUnlock::relock_text() const {
  const std::string name = field != nullptr ? std::string(field->name) : "lock";
  return "locking the EEPROM again (" + name + " " + std::to_string(kEepromUnlocked) + " -> " + std::to_string(read) +
         ")";
}

}  // namespace sms::modbus_map
