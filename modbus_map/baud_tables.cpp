#include "modbus_map/baud_tables.h"

#include <array>

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;

// docs/PROTOCOL.md §3, `feetech` column (sms1, sts). Codes 8-11 exist on sts firmware >= 2.45 only; the
// table's baud_rate field range says which codes a table accepts.
constexpr std::array<BaudEntry, 12> kFeetechBauds{{
    {0, 1'000'000},
    {1, 500'000},
    {2, 250'000},
    {3, 128'000},
    {4, 115'200},
    {5, 76'800},
    {6, 57'600},
    {7, 38'400},
    {8, 19'200},
    {9, 14'400},
    {10, 9'600},
    {11, 4'800},
}};

// docs/PROTOCOL.md §3, `modbus-rtu` column (SMSMB register 0x0B).
constexpr std::array<BaudEntry, 10> kModbusRtuBauds{{
    {0, 256'000},
    {1, 128'000},
    {2, 115'200},
    {3, 57'600},
    {4, 56'000},
    {5, 38'400},
    {6, 19'200},
    {7, 14'400},
    {8, 9'600},
    {9, 4'800},
}};

// docs/PROTOCOL.md §3, `d55d` column without code 0, whose rate depends on the motor kind (base motors
// 115200, others 9600): bps -> code answers 2 or 4 for those rates, never the ambiguous 0.
constexpr std::array<BaudEntry, 10> kD55dBauds{{
    {1, 2'400},
    {2, 9'600},
    {3, 38'400},
    {4, 115'200},
    {5, 256'000},
    {6, 460'800},
    {7, 896'000},
    {8, 921'600},
    {9, 1'280'000},
    {10, 1'792'000},
}};
constexpr std::uint8_t kD55dMotorKindCode = 0;
constexpr std::uint32_t kD55dCode0BaseMotor = 115'200;
constexpr std::uint32_t kD55dCode0Other = 9'600;

template <std::size_t N>
constexpr bool codes_ascending_and_rates_unique(const std::array<BaudEntry, N>& entries) {
  for (std::size_t i = 0; i < N; ++i) {
    if (i > 0 && entries[i].code <= entries[i - 1].code) return false;
    for (std::size_t j = i + 1; j < N; ++j) {
      if (entries[i].bps == entries[j].bps) return false;
    }
  }
  return true;
}
static_assert(codes_ascending_and_rates_unique(kFeetechBauds));
static_assert(codes_ascending_and_rates_unique(kModbusRtuBauds));
static_assert(codes_ascending_and_rates_unique(kD55dBauds));

}  // namespace

std::span<const BaudEntry> baud_table(BusProtocol protocol) {
  switch (protocol) {
    case BusProtocol::Feetech: return kFeetechBauds;
    case BusProtocol::ModbusRtu: return kModbusRtuBauds;
    case BusProtocol::D55d: return kD55dBauds;
  }
  return {};
}

std::optional<std::uint32_t> baud_from_code(BusProtocol protocol, std::uint8_t code, bool base_motor) {
  if (protocol == BusProtocol::D55d && code == kD55dMotorKindCode) {
    return base_motor ? kD55dCode0BaseMotor : kD55dCode0Other;
  }
  for (const BaudEntry& entry : baud_table(protocol)) {
    if (entry.code == code) return entry.bps;
  }
  return std::nullopt;
}

Expected<std::uint8_t> baud_code(BusProtocol protocol, std::uint32_t bps) {
  for (const BaudEntry& entry : baud_table(protocol)) {
    if (entry.bps == bps) return entry.code;
  }
  return unexpected(std::string(protocol::to_string(protocol)) + " bus: " + std::to_string(bps) +
                    " bps is not in the baud table (docs/PROTOCOL.md §3); valid rates: " + valid_bauds_text(protocol));
}

std::string valid_bauds_text(BusProtocol protocol) {
  std::string text;
  for (const BaudEntry& entry : baud_table(protocol)) {
    if (!text.empty()) text += ", ";
    text += std::to_string(entry.bps);
  }
  return text;
}

}  // namespace sms::modbus_map
