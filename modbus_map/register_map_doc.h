#pragma once
// The user-facing register map (docs/REGISTER_MAP.md), generated from the same data the
// gateway maps requests with: the control tables, the smsmb links and the baud tables.
#include <string>

namespace sms::modbus_map {

// The whole document, Markdown. `gen-register-map` prints it; a test compares it with the
// committed docs/REGISTER_MAP.md.
std::string register_map_markdown();

}  // namespace sms::modbus_map
