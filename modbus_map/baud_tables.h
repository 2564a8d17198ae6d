#pragma once
// Baud tables, one per bus protocol (docs/PROTOCOL.md §3), in both directions.
#include <cstdint>
#include <optional>
#include <span>
#include <string>

#include "protocol/bus_protocol.h"
#include "protocol/expected.h"

namespace sms::modbus_map {

struct BaudEntry {
  std::uint8_t code = 0;
  std::uint32_t bps = 0;
};

// Entries in code order. For d55d, code 0 is listed with its base-motor rate only through
// baud_from_code's `base_motor` flag; bps -> code never yields 0 there (codes 2/4 say it).
std::span<const BaudEntry> baud_table(protocol::BusProtocol protocol);

std::optional<std::uint32_t> baud_from_code(protocol::BusProtocol protocol, std::uint8_t code, bool base_motor = false);
// Error text names the protocol, the rejected rate and every valid rate.
Expected<std::uint8_t> baud_code(protocol::BusProtocol protocol, std::uint32_t bps);
// "1000000, 500000, ..." for messages.
std::string valid_bauds_text(protocol::BusProtocol protocol);

}  // namespace sms::modbus_map
