#pragma once
// The EEPROM lock (docs/PROTOCOL.md §4): on tables with a `lock` field (sts 55, sms1 48, scs 48,
// smsmb 0x85) an EEPROM write is lost at power-off unless the lock is 0 while it is written. A
// change meant to persist reads the lock, opens it when it is closed, makes the change, and writes
// the value it read back, also after a change that failed, so the servo is left as protected as
// it was. d55d has no lock: its EEPROM writes always persist. The one rule of the console's EEPROM
// writes (Modbus requests through the unit router) and of the tools' set-id and set-baud (frames
// on a line of their own); each does its own I/O.
//
//   const EepromUnlock lock{eeprom_lock(table), value_read_from_the_servo};
//   if (lock.needed()) write(lock.field, kEepromUnlocked), say(lock.unlock_text());
//   ... the change ...
//   if (lock.needed()) write(lock.field, lock.read), say(lock.relock_text());   // even if it failed
#include <cstdint>
#include <string>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

// The lock value with which EEPROM writes persist.
inline constexpr std::int32_t kEepromUnlocked = 0;

// The table's lock field, or nullptr when it has none (its EEPROM writes persist as they are).
const FieldSpec* eeprom_lock(const TableSpec& table);

// The lock writes around one persistent change, from the lock's value as read.
struct EepromUnlock {
  const FieldSpec* field = nullptr;  // eeprom_lock(); nullptr: no lock, nothing to write
  std::int32_t read = kEepromUnlocked;

  // Closed: kEepromUnlocked goes in before the change and `read` back after it.
  bool needed() const { return field != nullptr && read != kEepromUnlocked; }
  // "unlocking the EEPROM (lock 1 -> 0) so the change survives power-off"
  std::string unlock_text() const;
  // "locking the EEPROM again (lock 0 -> 1)"
  std::string relock_text() const;
};

}  // namespace sms::modbus_map
