#include "simulator/bus_spec.h"

#include <charconv>

#include "modbus_map/tables.h"

namespace sms::simulator {

using protocol::BusProtocol;

std::optional<std::uint32_t> parse_number(std::string_view text) {
  int base = 10;
  if (text.size() > 2 && text[0] == '0' && (text[1] == 'x' || text[1] == 'X')) {
    text.remove_prefix(2);
    base = 16;
  }
  std::uint32_t value = 0;
  const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value, base);
  if (text.empty() || error != std::errc() || end != text.data() + text.size()) return std::nullopt;
  return value;
}

std::optional<double> parse_probability(std::string_view text) {
  double value = 0;
  const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || error != std::errc() || end != text.data() + text.size() || value < 0 || value > 1) {
    return std::nullopt;
  }
  return value;
}

namespace {

// 'text' built by appending: GCC 12 at -O3 misreads `"'" + std::string(...)` as an overlapping
// memcpy (-Wrestrict, GCC bug 105651).
std::string quoted(std::string_view text) {
  std::string out(1, '\'');
  out.append(text);
  out.push_back('\'');
  return out;
}

Expected<std::uint8_t> parse_id(std::string_view text, std::string_view context) {
  const auto value = parse_number(text);
  if (!value || *value > 253) {
    return unexpected(quoted(text) + " in '" + std::string(context) + "' is not a servo ID (0-253)");
  }
  return static_cast<std::uint8_t>(*value);
}

std::vector<std::string_view> split(std::string_view text, char separator) {
  std::vector<std::string_view> parts;
  for (;;) {
    const auto at = text.find(separator);
    parts.push_back(text.substr(0, at));
    if (at == std::string_view::npos) return parts;
    text.remove_prefix(at + 1);
  }
}

}  // namespace

Expected<std::vector<std::uint8_t>> parse_id_list(std::string_view text) {
  std::vector<std::uint8_t> ids;
  for (const std::string_view part : split(text, ',')) {
    const auto dash = part.find('-');
    const auto first = parse_id(part.substr(0, dash), text);
    if (!first) return unexpected(first.error() + "; write IDs as 1-6 or 1,3,7");
    std::uint8_t last = *first;
    if (dash != std::string_view::npos) {
      const auto end = parse_id(part.substr(dash + 1), text);
      if (!end || *end < *first) {
        return unexpected(quoted(part) + " is not a range of servo IDs; write IDs as 1-6 or 1,3,7");
      }
      last = *end;
    }
    for (unsigned id = *first; id <= last; ++id) ids.push_back(static_cast<std::uint8_t>(id));
  }
  return ids;
}

protocol::BusProtocol protocol_of(modbus_map::TableId table) { return modbus_map::table(table).protocol; }

modbus_map::TableId default_table(BusProtocol protocol) {
  switch (protocol) {
    case BusProtocol::Feetech: return modbus_map::TableId::Sts;
    case BusProtocol::D55d: return modbus_map::TableId::D55d;
    case BusProtocol::ModbusRtu: return modbus_map::TableId::Smsmb;
  }
  return modbus_map::TableId::Sts;
}

std::uint32_t default_baud(BusProtocol protocol) { return protocol == BusProtocol::Feetech ? 1'000'000 : 115'200; }

Expected<ServoConfig> parse_servo_spec(std::string_view text) {
  const auto parts = split(text, ':');
  const std::string usage = "; write a servo as ID:TABLE:PROTOCOL:BAUD, e.g. 3:sts:feetech:1000000";
  if (parts.size() < 2 || parts.size() > 4) return unexpected(quoted(text) + " is not a servo" + usage);
  ServoConfig config;
  const auto id = parse_id(parts[0], text);
  if (!id) return unexpected(id.error() + usage);
  config.id = *id;
  const auto table = modbus_map::table_from_name(parts[1]);
  if (!table) return unexpected("unknown table '" + std::string(parts[1]) + "' (sts, sms1, scs, d55d, smsmb)" + usage);
  config.table = *table;
  config.protocol = protocol_of(*table);
  if (parts.size() >= 3 && !parts[2].empty()) {
    const auto protocol = protocol::bus_protocol_from_string(parts[2]);
    if (!protocol) {
      return unexpected("unknown protocol '" + std::string(parts[2]) + "' (feetech, d55d, modbus-rtu)" + usage);
    }
    if (*protocol != config.protocol) {
      return unexpected("table " + std::string(parts[1]) + " is spoken over " +
                        std::string(protocol::to_string(config.protocol)) + ", not " + std::string(parts[2]));
    }
  }
  config.baud = default_baud(config.protocol);
  if (parts.size() == 4) {
    const auto baud = parse_number(parts[3]);
    if (!baud || *baud == 0) return unexpected(quoted(parts[3]) + " is not a baud rate" + usage);
    config.baud = *baud;
  }
  return config;
}

Expected<std::pair<std::uint8_t, std::uint32_t>> parse_id_value(std::string_view text) {
  const auto colon = text.find(':');
  if (colon == std::string_view::npos) return unexpected(quoted(text) + " is not ID:VALUE");
  const auto id = parse_id(text.substr(0, colon), text);
  if (!id) return unexpected(id.error());
  const auto value = parse_number(text.substr(colon + 1));
  if (!value) return unexpected(quoted(text.substr(colon + 1)) + " in '" + std::string(text) + "' is not a number");
  return std::pair{*id, *value};
}

}  // namespace sms::simulator
