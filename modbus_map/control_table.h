#pragma once
// Control tables as data (SPEC §2): one FieldSpec per field, one TableSpec per table.
// The same lookup, encoding and register-mapping code serves every table.
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "protocol/bus_protocol.h"

namespace sms::modbus_map {

enum class TableId : std::uint8_t { Sts, Sms1, D55d, Smsmb };

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

// Which Modbus bit space a boolean field is also shown in (MODBUS_MAP.md "A servo unit").
enum class BitSpace : std::uint8_t { None, Coil, DiscreteInput };

struct FieldSpec {
  std::uint16_t addr = 0;       // byte address, or register number (Addressing::Register)
  std::string_view name;        // snake_case, stable: used in configs, dumps and docs
  std::uint8_t size = 1;        // bytes on the bus: 1 or 2 (a register is 2)
  Access access = Access::ReadWrite;
  Area area = Area::Ram;
  std::optional<std::int32_t> default_value;  // factory value where the documents give one
  Encoding encoding = kUnsigned;
  std::int32_t min = 0;         // valid range as a Modbus client sees the value
  std::int32_t max = 0;
  std::string_view unit;        // "0.1 V", "steps", "°C", "" ...
  BitSpace bit_space = BitSpace::None;
  std::string_view notes;       // one line for the generated register map
};

struct TableSpec {
  TableId id;
  std::string_view name;        // "sts", "sms1", "d55d", "smsmb"
  std::string_view title;       // human title for docs
  protocol::BusProtocol protocol;  // the only bus protocol this table is spoken over
  Addressing addressing;
  ByteOrder default_byte_order;
  std::span<const FieldSpec> fields;  // sorted by addr, non-overlapping
  bool has_sync_read;           // the poll cache may use one SYNC READ per cycle
};

}  // namespace sms::modbus_map
