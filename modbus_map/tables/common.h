#pragma once
// Shorthands shared by the table definitions (docs/PROTOCOL.md §2). Internal to modbus_map.
#include <array>
#include <cstdint>

#include "modbus_map/control_table.h"

namespace sms::modbus_map::tables {

// A writable one-byte field without a documented range takes 0-254 (docs/PROTOCOL.md §2.2 note).
inline constexpr std::int32_t kByteMax = 254;
// Read-only fields show whatever the servo holds: the full representable range.
inline constexpr std::int32_t kReadByteMax = 255;
inline constexpr std::int32_t kWordMax = 65535;
inline constexpr std::int32_t kInt16Min = -32768;
inline constexpr std::int32_t kInt16Max = 32767;
// Largest magnitude a sign-magnitude field with direction bit `bit` can carry.
constexpr std::int32_t sign_magnitude_max(std::uint8_t bit) { return (std::int32_t{1} << bit) - 1; }

inline constexpr Access R = Access::ReadOnly;
inline constexpr Access W = Access::WriteOnly;
inline constexpr Access RW = Access::ReadWrite;
inline constexpr Area Eeprom = Area::Eeprom;
inline constexpr Area Ram = Area::Ram;

// Torque enable on Feetech servos: 0 off, 1 on, 128 mid-point calibration (docs/PROTOCOL.md §2.1, §1.1).
inline constexpr std::array<std::int32_t, 3> kTorqueEnableValues{0, 1, 128};
// STS/SMS/SCS firmware also knows 2: damping, the motor free but braked (Feetech wiki memory-sts).
inline constexpr std::array<std::int32_t, 4> kTorqueEnableWithDampingValues{0, 1, 2, 128};
inline constexpr std::array<std::int32_t, 3> kTorqueSwitchWithDampingValues{0, 1, 2};

}  // namespace sms::modbus_map::tables
