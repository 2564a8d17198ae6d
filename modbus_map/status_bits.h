#pragma once
// The bits of a servo's status byte, kept with each table's data (TableSpec::status_bits): the
// ERROR byte of an FF FF answer (docs/PROTOCOL.md §1.1), D5 5D's (§1.2), and the low byte of
// smsmb's status register. One list for every place that names them: the bus monitor's decoded
// answers, the console's servo page, the register map, and the reason a refused motion write is given.
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

std::span<const StatusBit> status_bits(TableId table);
// The names of the fault bits set in `status` (a state such as smsmb's torque on is none); bits
// the table does not name as "bits 0x..".
std::vector<std::string> status_faults(TableId table, std::uint8_t status);

}  // namespace sms::modbus_map
