#pragma once
// The three kinds of bus the gateway drives (docs/PROTOCOL.md §1).
#include <cstdint>
#include <optional>
#include <string_view>

namespace sms::protocol {

enum class BusProtocol : std::uint8_t { Feetech, D55d, ModbusRtu };

// "feetech", "d55d", "modbus-rtu": the spelling used in configs and on command lines.
std::string_view to_string(BusProtocol protocol);
std::optional<BusProtocol> bus_protocol_from_string(std::string_view name);

}  // namespace sms::protocol
