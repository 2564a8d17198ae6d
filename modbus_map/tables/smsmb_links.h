#pragma once
// The smsmb profile (docs/PLC_GUIDE.md): each SMSMB register (docs/PROTOCOL.md §2.4) linked to its counterpart
// in the `sts` or `sms1` table, as data. A register not listed has no counterpart (0x02).
// Internal to modbus_map; the public view is smsmb_links() in register_map.h.
#include <array>

#include "modbus_map/register_map.h"
#include "modbus_map/tables/sms1.h"
#include "modbus_map/tables/smsmb.h"
#include "modbus_map/tables/sts.h"

namespace sms::modbus_map::tables {

// Designated initializers leave the members a row does not name at their defaults, on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"

// SMSMB mode 0 servo, 1 constant speed, 3 torque off on arrival (no counterpart), 4 stepper.
inline constexpr std::array<ValueMapping, 4> kStsModeMapping{{
    {0, 0, MapDirection::Both},
    {1, 1, MapDirection::Both},
    {4, 3, MapDirection::Both},      // stepper = sts step mode
    {2, 2, MapDirection::ReadOnly},  // sts open-loop PWM shows as SMSMB's reserved 2
}};
inline constexpr std::array<ValueMapping, 3> kSms1ModeMapping{{
    {0, 0, MapDirection::Both},
    {1, 1, MapDirection::Both},
    {2, 2, MapDirection::ReadOnly},  // sms1 torque mode shows as SMSMB's reserved 2
}};
// SMSMB lock 128 unlocks the factory area; on Feetech packet servos those fields are plain
// EEPROM, so "unlocked" is lock 0 (writes persist).
inline constexpr std::array<ValueMapping, 3> kLockMapping{{
    {0, 0, MapDirection::Both},
    {1, 1, MapDirection::Both},
    {128, 0, MapDirection::WriteOnly},
}};
// Status bits 0-3 and 5 mean the same on both; SMSMB bit 4 (torque on) is not in the feedback
// block and Feetech packet servos leave bit 4 unused, so it reads 0.
inline constexpr std::uint16_t kStatusMask = 0b0010'1111;

inline constexpr std::array kStsSmsmbLinks{
    CounterpartLink{.reg = 0x00,
                    .field_addr = 0,
                    .conversion = Conversion::BytePair,
                    .low_field_addr = 1,
                    .notes = "firmware major × 256 + minor"},
    CounterpartLink{.reg = 0x01,
                    .field_addr = 3,
                    .conversion = Conversion::BytePair,
                    .low_field_addr = 4,
                    .notes = "model major × 256 + minor"},
    CounterpartLink{.reg = 0x0A, .field_addr = 5},
    CounterpartLink{.reg = 0x0B, .field_addr = 6, .conversion = Conversion::BaudRate},
    CounterpartLink{.reg = 0x0C, .field_addr = 7, .conversion = Conversion::Scale, .scale_num = 2, .scale_den = 1},
    CounterpartLink{.reg = 0x0D, .field_addr = 9},
    CounterpartLink{.reg = 0x0E, .field_addr = 11},
    CounterpartLink{.reg = 0x0F, .field_addr = 31},
    CounterpartLink{.reg = 0x10, .field_addr = 33, .conversion = Conversion::ValueMap, .values = kStsModeMapping},
    CounterpartLink{.reg = 0x11, .field_addr = 21},
    CounterpartLink{.reg = 0x12, .field_addr = 22},
    CounterpartLink{.reg = 0x13, .field_addr = 23},
    CounterpartLink{.reg = 0x14, .field_addr = 37},
    CounterpartLink{.reg = 0x15, .field_addr = 39},
    CounterpartLink{.reg = 0x80, .field_addr = 42},
    CounterpartLink{.reg = 0x81, .field_addr = 40},
    CounterpartLink{.reg = 0x82, .field_addr = 41, .notes = "8.79 °/s² = 100 steps/s²"},
    CounterpartLink{.reg = 0x83, .field_addr = 46, .notes = "0.732 rpm on both at the factory phase (18 bit 2 clear)"},
    CounterpartLink{.reg = 0x84, .field_addr = 48},
    CounterpartLink{.reg = 0x85, .field_addr = 55, .conversion = Conversion::ValueMap, .values = kLockMapping},
    CounterpartLink{.reg = 0x86,
                    .field_addr = 40,
                    .conversion = Conversion::FaultReset,
                    .notes = "bit 2 writes 128 (calibrate to 2048)"},
    CounterpartLink{.reg = 0x100, .field_addr = 65, .conversion = Conversion::StatusBits, .status_mask = kStatusMask},
    CounterpartLink{.reg = 0x101, .field_addr = 56},
    CounterpartLink{.reg = 0x102, .field_addr = 58, .notes = "0.732 rpm on both at the factory phase (18 bit 2 clear)"},
    CounterpartLink{.reg = 0x103, .field_addr = 60},
    CounterpartLink{.reg = 0x104, .field_addr = 62},
    CounterpartLink{.reg = 0x105, .field_addr = 63},
    CounterpartLink{.reg = 0x106, .field_addr = 66},
    CounterpartLink{.reg = 0x107, .field_addr = 69},
    CounterpartLink{.reg = 0x185, .field_addr = 24},
    CounterpartLink{.reg = 0x186, .field_addr = 26},
    CounterpartLink{.reg = 0x187, .field_addr = 27},
    CounterpartLink{.reg = 0x188, .field_addr = 18},
    CounterpartLink{.reg = 0x189, .field_addr = 19},
    CounterpartLink{.reg = 0x18A, .field_addr = 20},
    CounterpartLink{.reg = 0x18B, .field_addr = 13},
    CounterpartLink{.reg = 0x18C, .field_addr = 14},
    CounterpartLink{.reg = 0x18D, .field_addr = 15},
    CounterpartLink{.reg = 0x18E, .field_addr = 28},
    CounterpartLink{.reg = 0x18F, .field_addr = 38, .conversion = Conversion::Scale, .scale_num = 10, .scale_den = 1},
    CounterpartLink{.reg = 0x190, .field_addr = 34, .conversion = Conversion::Scale, .scale_num = 10, .scale_den = 1},
    CounterpartLink{.reg = 0x191, .field_addr = 36, .conversion = Conversion::Scale, .scale_num = 10, .scale_den = 1},
    CounterpartLink{.reg = 0x192, .field_addr = 35, .conversion = Conversion::Scale, .scale_num = 10, .scale_den = 1},
    CounterpartLink{.reg = 0x193, .field_addr = 30},
    CounterpartLink{.reg = 0x194, .field_addr = 16, .notes = "max_torque is copied to torque_limit at power-on"},
};

// sms1 has no acceleration, torque limit, speed gains, firmware/model bytes or the protection
// timings, so fewer links; its layout differs (offset 33, mode 35, lock 48).
inline constexpr std::array kSms1SmsmbLinks{
    CounterpartLink{.reg = 0x00, .field_addr = 3, .notes = "software version"},
    CounterpartLink{.reg = 0x0A, .field_addr = 5},
    CounterpartLink{.reg = 0x0B, .field_addr = 6, .conversion = Conversion::BaudRate},
    CounterpartLink{.reg = 0x0C, .field_addr = 7, .conversion = Conversion::Scale, .scale_num = 2, .scale_den = 1},
    CounterpartLink{.reg = 0x0D, .field_addr = 9},
    CounterpartLink{.reg = 0x0E, .field_addr = 11},
    CounterpartLink{.reg = 0x0F, .field_addr = 33},
    CounterpartLink{.reg = 0x10, .field_addr = 35, .conversion = Conversion::ValueMap, .values = kSms1ModeMapping},
    CounterpartLink{.reg = 0x11, .field_addr = 21},
    CounterpartLink{.reg = 0x12, .field_addr = 22},
    CounterpartLink{.reg = 0x13, .field_addr = 23},
    CounterpartLink{.reg = 0x80, .field_addr = 42},
    CounterpartLink{.reg = 0x81, .field_addr = 40},
    CounterpartLink{.reg = 0x83,
                    .field_addr = 46,
                    .conversion = Conversion::Scale,
                    .scale_num = 1,
                    .scale_den = 50,
                    .notes = "0.732 rpm ≈ 50 × 0.087 °/s"},
    CounterpartLink{.reg = 0x85, .field_addr = 48, .conversion = Conversion::ValueMap, .values = kLockMapping},
    CounterpartLink{.reg = 0x86,
                    .field_addr = 40,
                    .conversion = Conversion::FaultReset,
                    .notes = "bit 2 writes 128 (calibrate to 2048, docs/PROTOCOL.md §1.1)"},
    CounterpartLink{.reg = 0x100, .field_addr = 65, .conversion = Conversion::StatusBits, .status_mask = kStatusMask},
    CounterpartLink{.reg = 0x101, .field_addr = 56},
    CounterpartLink{.reg = 0x102,
                    .field_addr = 58,
                    .conversion = Conversion::Scale,
                    .scale_num = 1,
                    .scale_den = 50,
                    .notes = "0.732 rpm ≈ 50 × 0.087 °/s"},
    CounterpartLink{.reg = 0x103, .field_addr = 60},
    CounterpartLink{.reg = 0x104, .field_addr = 62},
    CounterpartLink{.reg = 0x105, .field_addr = 63},
    CounterpartLink{.reg = 0x106, .field_addr = 66},
    CounterpartLink{.reg = 0x107, .field_addr = 69},
    CounterpartLink{.reg = 0x186, .field_addr = 26},
    CounterpartLink{.reg = 0x187, .field_addr = 27},
    CounterpartLink{.reg = 0x188, .field_addr = 18},
    CounterpartLink{.reg = 0x189, .field_addr = 19},
    CounterpartLink{.reg = 0x18A, .field_addr = 20},
    CounterpartLink{.reg = 0x18B, .field_addr = 13},
    CounterpartLink{.reg = 0x18C, .field_addr = 14},
    CounterpartLink{.reg = 0x18D, .field_addr = 15},
    CounterpartLink{.reg = 0x194, .field_addr = 16},
};

// Compile-time: every link names an SMSMB register and a field's first address of its table,
// links are sorted and unique, and BytePair halves are one byte each.
template <std::size_t N>
constexpr bool has_field_at(const std::array<FieldSpec, N>& fields, std::uint16_t addr, std::uint8_t size) {
  for (const FieldSpec& field : fields) {
    if (field.addr == addr) return size == 0 || field.size == size;
  }
  return false;
}
template <std::size_t L, std::size_t N>
constexpr bool links_consistent(const std::array<CounterpartLink, L>& links, const std::array<FieldSpec, N>& fields) {
  for (std::size_t i = 0; i < L; ++i) {
    const CounterpartLink& link = links[i];
    if (i > 0 && link.reg <= links[i - 1].reg) return false;
    if (!has_field_at(kSmsmbFields, link.reg, 0)) return false;
    const bool pair = link.conversion == Conversion::BytePair;
    if (!has_field_at(fields, link.field_addr, pair ? 1 : 0)) return false;
    if (pair && !has_field_at(fields, link.low_field_addr, 1)) return false;
    if (link.conversion == Conversion::Scale && (link.scale_num <= 0 || link.scale_den <= 0)) return false;
    if (link.conversion == Conversion::ValueMap && link.values.empty()) return false;
  }
  return true;
}
static_assert(links_consistent(kStsSmsmbLinks, kStsFields), "smsmb profile of sts: a link names no field");
static_assert(links_consistent(kSms1SmsmbLinks, kSms1Fields), "smsmb profile of sms1: a link names no field");

#pragma GCC diagnostic pop

}  // namespace sms::modbus_map::tables
