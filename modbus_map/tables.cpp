#include "modbus_map/tables.h"

#include <algorithm>
#include <array>
#include <cstdlib>
#include <stdexcept>
#include <string>

#include "modbus_map/tables/d55d.h"
#include "modbus_map/tables/scs.h"
#include "modbus_map/tables/sms1.h"
#include "modbus_map/tables/smsmb.h"
#include "modbus_map/tables/sts.h"
#include "protocol/hex_text.h"

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;

constexpr TableSpec kSts{
    .id = TableId::Sts,
    .name = "sts",
    .title = "STS/SMS servos (doc 001, FD tool table)",
    .protocol = BusProtocol::Feetech,
    .addressing = Addressing::Byte,
    .default_byte_order = ByteOrder::LowFirst,
    .fields = tables::kStsFields,
    .has_sync_read = true,
    .status_bits = tables::kStsStatusBits,
    .status_field = "status",
};
constexpr TableSpec kSms1{
    .id = TableId::Sms1,
    .name = "sms1",
    .title = "SMS 1.0 servos (doc 000)",
    .protocol = BusProtocol::Feetech,
    .addressing = Addressing::Byte,
    .default_byte_order = ByteOrder::LowFirst,
    .fields = tables::kSms1Fields,
    .has_sync_read = true,  // SYNC READ is STS/SMS (docs/PROTOCOL.md §1.1)
    .status_bits = tables::kSms1StatusBits,
    .status_field = "error",
};
constexpr TableSpec kD55d{
    .id = TableId::D55d,
    .name = "d55d",
    .title = "D5 5D vendor motors (doc 002)",
    .protocol = BusProtocol::D55d,
    .addressing = Addressing::Byte,
    .default_byte_order = ByteOrder::LowFirst,
    .fields = tables::kD55dFields,
    .has_sync_read = false,
    .status_bits = tables::kD55dStatusBits,
    .status_field = "",
};
constexpr TableSpec kSmsmb{
    .id = TableId::Smsmb,
    .name = "smsmb",
    .title = "SMSMB servos, Modbus-RTU firmware (Feetech wiki memory-smsmb)",
    .protocol = BusProtocol::ModbusRtu,
    .addressing = Addressing::Register,
    .default_byte_order = ByteOrder::HighFirst,
    .fields = tables::kSmsmbFields,
    .has_sync_read = false,
    .status_bits = tables::kSmsmbStatusBits,
    .status_field = "status",
};

constexpr TableSpec kScs{
    .id = TableId::Scs,
    .name = "scs",
    .title = "SCS servos (Feetech SCSCL SDK; high byte first)",
    .protocol = BusProtocol::Feetech,
    .addressing = Addressing::Byte,
    .default_byte_order = ByteOrder::HighFirst,
    .fields = tables::kScsFields,
    .has_sync_read = false,  // SYNC READ is STS/SMS only (docs/PROTOCOL.md §1.1)
    .status_bits = tables::kScsStatusBits,
    .status_field = "status",
};

// In TableId order.
constexpr std::array<const TableSpec*, 5> kTables{&kSts, &kSms1, &kD55d, &kSmsmb, &kScs};

constexpr bool tables_in_id_order() {
  for (std::size_t i = 0; i < kTables.size(); ++i) {
    if (static_cast<std::size_t>(kTables[i]->id) != i) return false;
  }
  return true;
}
static_assert(tables_in_id_order(), "kTables is indexed by TableId");

std::uint32_t width_mask(std::uint8_t size) { return size == 1 ? 0xFFu : 0xFFFFu; }

void check_size(std::size_t available, std::uint8_t size) {
  if (size != 1 && size != 2) {
    throw std::invalid_argument("field size " + std::to_string(size) + " is not 1 or 2 bytes");
  }
  if (available < size) {
    throw std::out_of_range("a " + std::to_string(size) + "-byte field needs " + std::to_string(size) + " bytes, " +
                            std::to_string(available) + " given");
  }
}

}  // namespace

const TableSpec& table(TableId id) {
  const auto index = static_cast<std::size_t>(id);
  if (index >= kTables.size()) throw std::out_of_range("no control table with id " + std::to_string(index));
  return *kTables[index];
}

std::span<const TableSpec* const> all_tables() { return kTables; }

std::optional<TableId> table_from_name(std::string_view name) {
  for (const TableSpec* spec : kTables) {
    if (spec->name == name) return spec->id;
  }
  return std::nullopt;
}

const FieldSpec* field_at(const TableSpec& table, std::uint16_t addr) {
  const auto it = std::lower_bound(table.fields.begin(), table.fields.end(), addr,
                                   [](const FieldSpec& field, std::uint16_t a) { return field.addr < a; });
  return it != table.fields.end() && it->addr == addr ? &*it : nullptr;
}

const FieldSpec* field_covering(const TableSpec& table, std::uint16_t addr) {
  // The last field starting at or before `addr`.
  const auto it = std::upper_bound(table.fields.begin(), table.fields.end(), addr,
                                   [](std::uint16_t a, const FieldSpec& field) { return a < field.addr; });
  if (it == table.fields.begin()) return nullptr;
  const FieldSpec& candidate = *std::prev(it);
  return addr < candidate.addr + address_span(table.addressing, candidate) ? &candidate : nullptr;
}

const FieldSpec* field_by_name(const TableSpec& table, std::string_view name) {
  for (const FieldSpec& field : table.fields) {
    if (field.name == name) return &field;
  }
  return nullptr;
}

std::uint16_t end_address(const TableSpec& table) {
  if (table.fields.empty()) return 0;
  const FieldSpec& last = table.fields.back();
  return static_cast<std::uint16_t>(last.addr + address_span(table.addressing, last));
}

std::int32_t decode_value(const FieldSpec& field, std::uint32_t raw) {
  raw &= width_mask(field.size);
  switch (field.encoding.kind) {
    case EncodingKind::Unsigned: return static_cast<std::int32_t>(raw);
    case EncodingKind::SignMagnitude: {
      // Bits above the direction bit are not part of the value (docs/PROTOCOL.md §4).
      const std::uint32_t direction = std::uint32_t{1} << field.encoding.sign_bit;
      const auto magnitude = static_cast<std::int32_t>(raw & (direction - 1));
      return (raw & direction) != 0 ? -magnitude : magnitude;
    }
    case EncodingKind::TwosComplement: {
      const std::uint32_t sign = std::uint32_t{1} << (field.size * 8 - 1);
      const auto value = static_cast<std::int32_t>(raw);
      return (raw & sign) != 0 ? value - static_cast<std::int32_t>(sign << 1) : value;
    }
  }
  return static_cast<std::int32_t>(raw);
}

std::optional<std::uint32_t> encode_value(const FieldSpec& field, std::int32_t value) {
  if (value < field.min || value > field.max) return std::nullopt;
  if (!field.allowed_values.empty() &&
      std::find(field.allowed_values.begin(), field.allowed_values.end(), value) == field.allowed_values.end()) {
    return std::nullopt;
  }
  const std::uint32_t mask = width_mask(field.size);
  switch (field.encoding.kind) {
    case EncodingKind::Unsigned:
      if (value < 0 || static_cast<std::uint32_t>(value) > mask) return std::nullopt;
      return static_cast<std::uint32_t>(value);
    case EncodingKind::SignMagnitude: {
      const std::uint32_t direction = std::uint32_t{1} << field.encoding.sign_bit;
      const auto magnitude = static_cast<std::uint32_t>(std::abs(value));
      if (magnitude >= direction || direction > mask) return std::nullopt;
      return (value < 0 ? direction : 0u) | magnitude;
    }
    case EncodingKind::TwosComplement: {
      const std::int32_t largest = static_cast<std::int32_t>(mask >> 1);
      if (value < -largest - 1 || value > largest) return std::nullopt;
      return static_cast<std::uint32_t>(value) & mask;
    }
  }
  return std::nullopt;
}

std::uint32_t load_raw(std::span<const std::uint8_t> bytes, std::uint8_t size, ByteOrder order) {
  check_size(bytes.size(), size);
  if (size == 1) return bytes[0];
  const std::uint8_t low = order == ByteOrder::LowFirst ? bytes[0] : bytes[1];
  const std::uint8_t high = order == ByteOrder::LowFirst ? bytes[1] : bytes[0];
  return static_cast<std::uint32_t>(high) << 8 | low;
}

void store_raw(std::span<std::uint8_t> bytes, std::uint8_t size, ByteOrder order, std::uint32_t raw) {
  check_size(bytes.size(), size);
  if (size == 1) {
    bytes[0] = static_cast<std::uint8_t>(raw);
    return;
  }
  const auto low = static_cast<std::uint8_t>(raw & 0xFF);
  const auto high = static_cast<std::uint8_t>((raw >> 8) & 0xFF);
  bytes[0] = order == ByteOrder::LowFirst ? low : high;
  bytes[1] = order == ByteOrder::LowFirst ? high : low;
}

std::string address_text(const TableSpec& table, std::uint32_t address) {
  return table.addressing == Addressing::Register ? protocol::hex_number(address) : std::to_string(address);
}

std::string range_text(std::int32_t min, std::int32_t max) { return std::to_string(min) + ".." + std::to_string(max); }

}  // namespace sms::modbus_map
