#pragma once
// Text forms of a bus description, shared by the sms-sim command line and the control
// socket: ID lists ("1-6", "1,3,7", "1-3,7"), servo specs ("ID:TABLE:PROTOCOL:BAUD") and
// "ID:VALUE" pairs. Errors say what was expected.
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "modbus_map/control_table.h"
#include "protocol/bus_protocol.h"
#include "protocol/expected.h"
#include "simulator/simulated_bus.h"

namespace sms::simulator {

// Decimal, or hexadecimal with 0x. nullopt for anything else (signs, trailing text).
std::optional<std::uint32_t> parse_number(std::string_view text);
// A probability 0..1.
std::optional<double> parse_probability(std::string_view text);

Expected<std::vector<std::uint8_t>> parse_id_list(std::string_view text);
// "ID:TABLE[:PROTOCOL[:BAUD]]": a missing protocol is the table's, a missing baud the
// protocol's factory default.
Expected<ServoConfig> parse_servo_spec(std::string_view text);
// "ID:VALUE" with VALUE a number.
Expected<std::pair<std::uint8_t, std::uint32_t>> parse_id_value(std::string_view text);

// The only protocol a table is spoken over, and the table a protocol's servos default to.
protocol::BusProtocol protocol_of(modbus_map::TableId table);
modbus_map::TableId default_table(protocol::BusProtocol protocol);
// Factory rates (docs/PROTOCOL.md §3): STS 1 000 000; d55d base motors and SMSMB 115 200.
std::uint32_t default_baud(protocol::BusProtocol protocol);

}  // namespace sms::simulator
