#include "simulator/servo_memory.h"

#include <algorithm>

#include "modbus_map/tables.h"

namespace sms::simulator {

using modbus_map::Addressing;
using modbus_map::FieldSpec;

ServoMemory::ServoMemory(const modbus_map::TableSpec& table)
    : table_(&table),
      // A register goes on the wire high byte first whatever the table's default says (Modbus).
      byte_order_(table.addressing == Addressing::Register ? modbus_map::ByteOrder::HighFirst
                                                           : table.default_byte_order),
      unit_size_(table.addressing == Addressing::Register ? 2 : 1),
      end_address_(modbus_map::end_address(table)),
      bytes_(static_cast<std::size_t>(end_address_) * unit_size_, 0) {}

bool ServoMemory::contains(std::uint32_t address, std::uint32_t count) const {
  return count > 0 && address < end_address_ && count <= static_cast<std::uint32_t>(end_address_) - address;
}

std::span<const std::uint8_t> ServoMemory::field_bytes(const FieldSpec& field) const {
  return std::span<const std::uint8_t>(bytes_).subspan(field.addr * unit_size_, field.size);
}

std::uint32_t ServoMemory::raw(const FieldSpec& field) const {
  return modbus_map::load_raw(field_bytes(field), field.size, byte_order_);
}

void ServoMemory::set_raw(const FieldSpec& field, std::uint32_t raw) {
  modbus_map::store_raw(std::span<std::uint8_t>(bytes_).subspan(field.addr * unit_size_, field.size), field.size,
                        byte_order_, raw);
}

std::int32_t ServoMemory::value(const FieldSpec& field) const { return modbus_map::decode_value(field, raw(field)); }

void ServoMemory::store_value(const FieldSpec& field, std::int64_t value) {
  const auto clamped = static_cast<std::int32_t>(std::clamp<std::int64_t>(value, field.min, field.max));
  if (const auto raw = modbus_map::encode_value(field, clamped)) set_raw(field, *raw);
}

bool ServoMemory::accepts(const FieldSpec& field, std::uint32_t raw) {
  const std::int32_t value = modbus_map::decode_value(field, raw);
  if (value < field.min || value > field.max) return false;
  if (!field.allowed_values.empty() &&
      std::find(field.allowed_values.begin(), field.allowed_values.end(), value) == field.allowed_values.end()) {
    return false;
  }
  const auto encoded = modbus_map::encode_value(field, value);
  // Sign-magnitude has two zeros; a host sending "-0" (direction bit, no magnitude) is fine.
  return encoded && (*encoded == raw || value == 0);
}

std::span<const std::uint8_t> ServoMemory::wire(std::uint16_t address, std::uint16_t count) const {
  return std::span<const std::uint8_t>(bytes_).subspan(address * unit_size_, count * unit_size_);
}

std::span<std::uint8_t> ServoMemory::wire(std::uint16_t address, std::uint16_t count) {
  return std::span<std::uint8_t>(bytes_).subspan(address * unit_size_, count * unit_size_);
}

void ServoMemory::reset_area(modbus_map::Area area) {
  for (const FieldSpec& field : table_->fields) {
    if (field.area != area) continue;
    set_raw(field, 0);
    if (field.default_value) store_value(field, *field.default_value);
  }
}

}  // namespace sms::simulator
