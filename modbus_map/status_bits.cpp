#include "modbus_map/status_bits.h"

#include <array>
#include <cstdio>

#include "protocol/d55d.h"
#include "protocol/feetech.h"

namespace sms::modbus_map {
namespace {

constexpr std::array<StatusBit, 6> kFeetechStatusBits{{
    {protocol::feetech::error_bit::kVoltage, "voltage"},
    {protocol::feetech::error_bit::kAngleSensor, "angle_sensor"},
    {protocol::feetech::error_bit::kTemperature, "temperature"},
    {protocol::feetech::error_bit::kCurrent, "current"},
    {protocol::feetech::error_bit::kAngle, "angle"},
    {protocol::feetech::error_bit::kOverload, "overload"},
}};
constexpr std::array<StatusBit, 7> kD55dStatusBits{{
    {protocol::d55d::error_bit::kOverTemperature, "over_temperature"},
    {protocol::d55d::error_bit::kOverCurrent, "over_current"},
    {protocol::d55d::error_bit::kOverVoltage, "over_voltage"},
    {protocol::d55d::error_bit::kUnderVoltage, "under_voltage"},
    {protocol::d55d::error_bit::kChecksum, "checksum"},
    {protocol::d55d::error_bit::kInstruction, "instruction"},
    {protocol::d55d::error_bit::kStall, "stall"},
}};
// smsmb's status register (0x86's bits, docs/PROTOCOL.md §2.3), low byte.
constexpr std::array<StatusBit, 6> kSmsmbStatusBits{{
    {1 << 0, "overload"},
    {1 << 1, "current"},
    {1 << 2, "centre_set"},
    {1 << 5, "voltage"},
    {1 << 6, "temperature"},
    {1 << 7, "encoder"},
}};

}  // namespace

std::span<const StatusBit> status_bits(TableId table) {
  switch (table) {
    case TableId::Smsmb: return kSmsmbStatusBits;
    case TableId::D55d: return kD55dStatusBits;
    case TableId::Sts:
    case TableId::Sms1:
    case TableId::Scs: break;
  }
  return kFeetechStatusBits;
}

std::vector<std::string> status_faults(TableId table, std::uint8_t status) {
  std::vector<std::string> names;
  std::uint8_t known = 0;
  for (const auto& bit : status_bits(table)) {
    known |= bit.mask;
    if ((status & bit.mask) != 0) names.emplace_back(bit.name);
  }
  if ((status & ~known & 0xFF) != 0) {
    char text[16];
    std::snprintf(text, sizeof text, "bits 0x%02x", static_cast<unsigned>(status & ~known & 0xFF));
    names.emplace_back(text);
  }
  return names;
}

}  // namespace sms::modbus_map
