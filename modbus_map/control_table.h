#pragma once
// Control tables as data (docs/PROTOCOL.md §2): one FieldSpec per field, one TableSpec per table.
// The same lookup, encoding and register-mapping code serves every table.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "protocol/bus_protocol.h"

namespace sms::modbus_map {

enum class TableId : std::uint8_t { Sts, Sms1, D55d, Smsmb, Scs };

enum class Access : std::uint8_t { ReadOnly, WriteOnly, ReadWrite };
enum class Area : std::uint8_t { Eeprom, Ram };
enum class ByteOrder : std::uint8_t { LowFirst, HighFirst };
// Byte: packet tables, one address per byte. Register: SMSMB, one address per 16-bit register.
enum class Addressing : std::uint8_t { Byte, Register };

enum class EncodingKind : std::uint8_t {
  Unsigned,
  SignMagnitude,   // `sign_bit` is the direction, the bits below it the magnitude
  TwosComplement,  // over the field's size
};
struct Encoding {
  EncodingKind kind = EncodingKind::Unsigned;
  std::uint8_t sign_bit = 0;  // SignMagnitude only
};
inline constexpr Encoding kUnsigned{};
inline constexpr Encoding sign_magnitude(std::uint8_t bit) { return {EncodingKind::SignMagnitude, bit}; }
inline constexpr Encoding kTwosComplement{EncodingKind::TwosComplement, 0};

// Which Modbus bit space a boolean field is also shown in (docs/PLC_GUIDE.md "A servo unit").
enum class BitSpace : std::uint8_t { None, Coil, DiscreteInput };

struct FieldSpec {
  std::uint16_t addr = 0;  // byte address, or register number (Addressing::Register)
  std::string_view name;   // snake_case, stable: used in configs, dumps and docs
  std::uint8_t size = 1;   // bytes on the bus: 1 or 2 (a register is 2)
  Access access = Access::ReadWrite;
  Area area = Area::Ram;
  std::optional<std::int32_t> default_value;  // factory value where the documents give one
  Encoding encoding = kUnsigned;
  std::int32_t min = 0;  // valid range as a Modbus client sees the value
  std::int32_t max = 0;
  std::string_view unit;  // "0.1 V", "steps", "°C", "" ...
  BitSpace bit_space = BitSpace::None;
  std::string_view notes;  // one line for the generated register map
  // When not empty, the only values a write may carry (inside [min, max]); e.g. sts torque
  // enable: 0, 1 and 128 (mid-point calibration), nothing in between.
  std::span<const std::int32_t> allowed_values = {};
};

// One bit of a servo's status byte: the ERROR byte of a packet table's answers (docs/PROTOCOL.md
// §1.1, §1.2), the low byte of smsmb's status register 0x100 (§2.3).
struct StatusBit {
  std::uint8_t mask = 0;  // one bit
  std::string_view name;  // snake_case: the console, the bus monitor and refusal reasons show it
  bool fault = true;      // false: a state the byte reports (smsmb bit 4, torque on), never a fault
};

struct TableSpec {
  TableId id;
  std::string_view name;           // "sts", "sms1", "d55d", "smsmb", "scs"
  std::string_view title;          // human title for docs
  protocol::BusProtocol protocol;  // the only bus protocol this table is spoken over
  Addressing addressing;
  ByteOrder default_byte_order;
  std::span<const FieldSpec> fields;       // sorted by addr, non-overlapping
  bool has_sync_read;                      // the poll cache may use one SYNC READ per cycle
  std::span<const StatusBit> status_bits;  // the bits its servos' status byte has, by name
  std::string_view status_field;           // the field that holds that byte too; "": answers only (d55d)
};

// Bus address units one field address stands for: a byte on packet tables, a 16-bit register
// (two bytes on the wire) on SMSMB.
constexpr std::uint8_t bytes_per_address(Addressing addressing) { return addressing == Addressing::Register ? 2 : 1; }
// Addresses a field occupies: its size in bytes on packet tables, always one register on SMSMB.
constexpr std::uint16_t address_span(Addressing addressing, const FieldSpec& field) {
  return addressing == Addressing::Register ? 1 : field.size;
}

// Every status bit one bit of its own, named once.
constexpr bool status_bits_well_formed(std::span<const StatusBit> bits) {
  std::uint8_t seen = 0;
  for (std::size_t i = 0; i < bits.size(); ++i) {
    const std::uint8_t mask = bits[i].mask;
    if (mask == 0 || (mask & (mask - 1)) != 0 || (seen & mask) != 0 || bits[i].name.empty()) return false;
    seen |= mask;
    for (std::size_t j = i + 1; j < bits.size(); ++j) {
      if (bits[j].name == bits[i].name) return false;
    }
  }
  return true;
}

// The compile-time checks every table gets: fields sorted by address, no two
// fields sharing an address, sizes 1 or 2 (a register is 2), min <= max, a default inside
// the range, and names unique.
constexpr bool fields_sorted_and_disjoint(std::span<const FieldSpec> fields, Addressing addressing) {
  for (std::size_t i = 0; i < fields.size(); ++i) {
    const FieldSpec& field = fields[i];
    if (field.size != 1 && field.size != 2) return false;
    if (addressing == Addressing::Register && field.size != 2) return false;
    if (i + 1 < fields.size() && field.addr + address_span(addressing, field) > fields[i + 1].addr) return false;
  }
  return true;
}
// [min, max] fits the field's size and encoding.
constexpr bool range_representable(const FieldSpec& field) {
  const int bits = field.size * 8;
  switch (field.encoding.kind) {
    case EncodingKind::Unsigned: return field.min >= 0 && field.max < (std::int64_t{1} << bits);
    case EncodingKind::SignMagnitude: {
      if (field.encoding.sign_bit >= bits) return false;
      const std::int64_t largest = (std::int64_t{1} << field.encoding.sign_bit) - 1;
      return field.min >= -largest && field.max <= largest;
    }
    case EncodingKind::TwosComplement:
      return field.min >= -(std::int64_t{1} << (bits - 1)) && field.max < (std::int64_t{1} << (bits - 1));
  }
  return false;
}
constexpr bool fields_well_formed(std::span<const FieldSpec> fields) {
  for (std::size_t i = 0; i < fields.size(); ++i) {
    const FieldSpec& field = fields[i];
    if (field.name.empty() || field.min > field.max) return false;
    if (!range_representable(field)) return false;
    if (field.default_value && (*field.default_value < field.min || *field.default_value > field.max)) return false;
    for (const std::int32_t allowed : field.allowed_values) {
      if (allowed < field.min || allowed > field.max) return false;
    }
    if (field.bit_space == BitSpace::Coil && (field.access != Access::ReadWrite || field.min != 0)) return false;
    if (field.bit_space == BitSpace::DiscreteInput && field.access != Access::ReadOnly) return false;
    for (std::size_t j = i + 1; j < fields.size(); ++j) {
      if (fields[j].name == field.name) return false;
    }
  }
  return true;
}

}  // namespace sms::modbus_map
