#pragma once
// The four control tables (docs/PROTOCOL.md §2.1-2.4) and lookups over them.
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

const TableSpec& table(TableId id);
std::span<const TableSpec* const> all_tables();
std::optional<TableId> table_from_name(std::string_view name);

// The field whose first address is `addr`, or nullptr.
const FieldSpec* field_at(const TableSpec& table, std::uint16_t addr);
// The field occupying `addr` (first or second byte), or nullptr.
const FieldSpec* field_covering(const TableSpec& table, std::uint16_t addr);
const FieldSpec* field_by_name(const TableSpec& table, std::string_view name);
// One past the highest address any field occupies.
std::uint16_t end_address(const TableSpec& table);

// An address as the table's documents write it: hex for register tables ("0x0A"), decimal for
// byte tables.
std::string address_text(const TableSpec& table, std::uint32_t address);
// "min..max".
std::string range_text(std::int32_t min, std::int32_t max);

// Raw bus value <-> the value a Modbus client sees (sign-magnitude and two's complement
// become signed; docs/PROTOCOL.md §4).
std::int32_t decode_value(const FieldSpec& field, std::uint32_t raw);
// nullopt when `value` is outside [field.min, field.max] or not representable.
std::optional<std::uint32_t> encode_value(const FieldSpec& field, std::int32_t value);

// Raw field bytes <-> raw value, in the given byte order.
std::uint32_t load_raw(std::span<const std::uint8_t> bytes, std::uint8_t size, ByteOrder order);
void store_raw(std::span<std::uint8_t> bytes, std::uint8_t size, ByteOrder order, std::uint32_t raw);

}  // namespace sms::modbus_map
