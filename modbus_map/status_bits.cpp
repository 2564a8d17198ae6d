#include "modbus_map/status_bits.h"

#include <cstdio>

#include "modbus_map/tables.h"

namespace sms::modbus_map {

std::span<const StatusBit> status_bits(TableId table) { return modbus_map::table(table).status_bits; }

std::vector<std::string> status_faults(TableId table, std::uint8_t status) {
  std::vector<std::string> names;
  std::uint8_t known = 0;
  for (const auto& bit : status_bits(table)) {
    known |= bit.mask;
    if (bit.fault && (status & bit.mask) != 0) names.emplace_back(bit.name);
  }
  if ((status & ~known & 0xFF) != 0) {
    char text[16];
    std::snprintf(text, sizeof text, "bits 0x%02x", static_cast<unsigned>(status & ~known & 0xFF));
    names.emplace_back(text);
  }
  return names;
}

}  // namespace sms::modbus_map
