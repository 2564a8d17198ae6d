#pragma once
// The integrator tools that change or show one servo: set-id, set-baud, calibrate-middle, dump.
// Library code over a ServoLink (tool_link.h); tool_cli.cpp is the thin command line on top.
//
// Each refuses the dangerous mistakes before touching the servo, with a message that says
// what to do instead: a target ID already answering, a baud outside the protocol's table (or
// outside what the table's baud field accepts), the broadcast ID without `force`.
//
// EEPROM (docs/PROTOCOL.md §4): on tables with a lock field (sts 55, sms1 48, scs 48, smsmb 0x85)
// an EEPROM write is lost at power-off unless the lock is 0 while it is written. set-id and
// set-baud read the lock, write 0, make the change, then write the lock's previous value back —
// so the change persists and the servo is left as protected as it was; the console's EEPROM
// writes follow the same rule (modbus_map/eeprom_lock.h). d55d has no lock: its EEPROM writes
// always persist.
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "gateway/tools/tool_link.h"
#include "modbus_map/control_table.h"
#include "protocol/expected.h"

namespace sms::gateway {

// Progress lines for the user ("unlocking the EEPROM (lock 1 -> 0)").
using Say = std::function<void(const std::string&)>;

struct ToolTarget {
  modbus_map::TableId table = modbus_map::TableId::Sts;  // must be spoken by the link's protocol
  std::uint8_t id = 1;  // the protocol's broadcast ID (254, or 0 on modbus-rtu) needs `force`
  bool force = false;
};

// Gives the servo `target.id` the ID `new_id`: checks the servo answers and `new_id` is free,
// unlocks, writes the ID, relocks under the new ID, verifies (PING and READ on the new ID).
// The result is the one-line summary.
Expected<std::string> set_servo_id(ServoLink& link, const ToolTarget& target, std::uint8_t new_id, const Say& say);

// Moves the servo to `new_baud` (a rate of its protocol's table): writes the protocol's own
// baud code with the EEPROM unlocked, switches the link to the new rate, relocks there and
// verifies the servo answers and holds the code. The link is left at `new_baud`.
Expected<std::string> set_servo_baud(ServoLink& link, const ToolTarget& target, std::uint32_t new_baud, const Say& say);

// Mid-point calibration: the present position becomes the centre (2048).
// sts: 128 to torque enable (address 40); smsmb: fault reset (0x86) bit 2. Other tables have
// no documented calibration and are refused.
Expected<std::string> calibrate_middle(ServoLink& link, const ToolTarget& target, const Say& say);

// Factory reset, where the protocol has an instruction for it (ToolProtocol::factory_reset:
// d55d RESET): checks the servo answers and the factory ID is free at this rate, sends it, then
// finds the servo at its factory ID and baud (the link is left there). Refused elsewhere, saying
// what to do instead.
Expected<std::string> factory_reset(ServoLink& link, const ToolTarget& target, const Say& say);

struct DumpRow {
  const modbus_map::FieldSpec* field = nullptr;
  std::uint32_t raw = 0;
  std::int32_t value = 0;  // as a Modbus client sees it (signed where the field is)
};
// Every field of the table, read in as few READs / FC03s as the table allows.
Expected<std::vector<DumpRow>> dump_servo(ServoLink& link, const ToolTarget& target);
// address, name, value, unit, access, area — one line per field, with a header.
std::string format_dump(const modbus_map::TableSpec& table, const std::vector<DumpRow>& rows);

}  // namespace sms::gateway
