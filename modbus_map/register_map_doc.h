#pragma once
// The user-facing register map (docs/REGISTER_MAP.md), generated from the same data the
// gateway maps requests with: the control tables, the smsmb links and the baud tables.
#include <string>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

// The writes of table `id` that enable motion ("no jump on enable"), one line of Markdown from
// its MotionSpec: "`torque_enable` := 1 (torque on); a write of `operating_mode` that changes the drive". In the
// register map and in docs/SAFETY.md's table (a test checks they agree).
std::string enabling_writes_text(TableId id);

// The whole document, Markdown. `gen-register-map` prints it; a test compares it with the
// committed docs/REGISTER_MAP.md.
std::string register_map_markdown();

}  // namespace sms::modbus_map
