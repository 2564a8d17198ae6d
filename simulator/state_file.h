#pragma once
// The state file: the EEPROM of each servo slot as it would survive a power cycle, plus its
// BACKUP image, so `sms-sim --state-file` keeps unlocked EEPROM writes across restarts.
// One line per image, readable and diffable:
//   eeprom 0 sts id=1 baud_rate=0 return_delay=250 ...
//   backup 0 sts id=1 ...
// The number is the servo's slot (its position on the command line), so a servo whose ID was
// changed and saved comes back with its new ID.
#include <cstddef>
#include <map>
#include <string>

#include "simulator/virtual_servo.h"

namespace sms::simulator {

struct PersistedServo {
  std::string table;  // modbus_map table name; a slot whose table changed is not loaded
  FieldValues eeprom;
  FieldValues backup;
};
using PersistedState = std::map<std::size_t, PersistedServo>;

// A missing file is an empty state. Throws std::runtime_error naming file:line for a line
// that cannot be read.
PersistedState load_state_file(const std::string& path);
// Written to a temporary file and renamed over `path`. Throws std::system_error.
void save_state_file(const std::string& path, const PersistedState& state);

}  // namespace sms::simulator
