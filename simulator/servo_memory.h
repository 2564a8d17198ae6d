#pragma once
// One servo's control-table image, laid out as the bus sees it: byte tables one byte per
// address, SMSMB one 16-bit register (high byte first) per address. Layout, sizes, byte
// order, encodings and ranges all come from the modbus_map TableSpec (docs/PROTOCOL.md §2).
#include <cstdint>
#include <span>

#include "modbus_map/control_table.h"
#include "protocol/packet.h"

namespace sms::simulator {

class ServoMemory {
 public:
  explicit ServoMemory(const modbus_map::TableSpec& table);

  const modbus_map::TableSpec& table() const { return *table_; }
  modbus_map::ByteOrder byte_order() const { return byte_order_; }
  // Bytes per address: 1, or 2 for register tables.
  std::size_t unit_size() const { return unit_size_; }
  std::uint16_t end_address() const { return end_address_; }
  bool contains(std::uint32_t address, std::uint32_t count) const;

  std::uint32_t raw(const modbus_map::FieldSpec& field) const;
  void set_raw(const modbus_map::FieldSpec& field, std::uint32_t raw);
  // Decoded as a Modbus client sees it (sign-magnitude and two's complement become signed).
  std::int32_t value(const modbus_map::FieldSpec& field) const;
  // Clamped into the field's range, then encoded.
  void store_value(const modbus_map::FieldSpec& field, std::int64_t value);
  // A raw value the field accepts: within [min, max] and in the field's encoding.
  static bool accepts(const modbus_map::FieldSpec& field, std::uint32_t raw);

  // Wire bytes of `count` addresses from `address`; the caller checked contains().
  std::span<const std::uint8_t> wire(std::uint16_t address, std::uint16_t count) const;
  std::span<std::uint8_t> wire(std::uint16_t address, std::uint16_t count);

  // Every field of `area` back to its factory default (0 where the documents give none).
  void reset_area(modbus_map::Area area);

 private:
  std::span<const std::uint8_t> field_bytes(const modbus_map::FieldSpec& field) const;

  const modbus_map::TableSpec* table_;
  modbus_map::ByteOrder byte_order_;
  std::size_t unit_size_;
  std::uint16_t end_address_;
  protocol::Bytes bytes_;
};

}  // namespace sms::simulator
