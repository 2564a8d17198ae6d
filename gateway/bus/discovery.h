#pragma once
// Discovery at bus start: PING every configured servo, read its identity where the
// table has one, and log a one-screen summary. This header holds the data and the text; the
// bus engine runs the transactions.
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "gateway/bus/poll_cache.h"
#include "modbus_map/control_table.h"

namespace sms::gateway {

// How one identity value sits in the bytes read at discovery.
enum class IdentityFormat : std::uint8_t {
  MajorMinor,   // two one-byte fields, major first; shown "8.42"
  Value,        // one field in the servo's byte order; shown in decimal, two bytes in hex
  ModelNumber,  // two bytes read as one word in the servo's byte order, as Feetech's SDKs and
                // FD tool read the model (10760); shown with the model's name when known
};
struct IdentityField {
  std::uint8_t offset = 0;  // into the bytes read
  std::uint8_t size = 1;
  IdentityFormat format = IdentityFormat::Value;
};
struct IdentityLayout {
  modbus_map::TableId table;
  AddressBlock read;  // one READ covering every field below (bus addresses: registers on smsmb)
  std::optional<IdentityField> model;
  std::optional<IdentityField> firmware;
  // The table's `response_level` field (one byte) in the bytes read; SMSMB servos have none
  // (a Modbus slave answers every unicast request).
  std::optional<std::uint8_t> response_level_offset;

  std::optional<std::uint16_t> response_level_address() const {
    if (!response_level_offset) return std::nullopt;
    return static_cast<std::uint16_t>(read.address + *response_level_offset);
  }
};

// sts and scs: firmware 0-1, byte-order flag 2, model number 3-4, response level 8 (docs/PROTOCOL.md §2.1,
// modbus_map/tables/scs.h); sms1: software version 3-4, response level 8 (§2.2); d55d: vendor
// code 0, software version 2, response level 16 (§2.3); smsmb: registers 0x00 firmware version
// and 0x01 servo (model) version, two bytes each, high byte first (§2.4).
inline constexpr std::array<IdentityLayout, 5> kIdentityLayouts{{
    {modbus_map::TableId::Sts,
     {0, 9},
     IdentityField{3, 2, IdentityFormat::ModelNumber},
     IdentityField{0, 2, IdentityFormat::MajorMinor},
     8},
    {modbus_map::TableId::Scs,
     {0, 9},
     IdentityField{3, 2, IdentityFormat::ModelNumber},
     IdentityField{0, 2, IdentityFormat::MajorMinor},
     8},
    {modbus_map::TableId::Sms1, {3, 6}, std::nullopt, IdentityField{0, 2, IdentityFormat::Value}, 5},
    {modbus_map::TableId::D55d,
     {0, 17},
     IdentityField{0, 1, IdentityFormat::Value},
     IdentityField{2, 1, IdentityFormat::Value},
     16},
    {modbus_map::TableId::Smsmb,
     {0, 2},
     IdentityField{2, 2, IdentityFormat::Value},
     IdentityField{0, 2, IdentityFormat::Value},
     std::nullopt},
}};

const IdentityLayout* identity_layout(modbus_map::TableId table);

// Address 2 of STS/SMS and SCS servos says how they store two-byte fields (Feetech wiki
// memory-sts "END": 0 low byte first; SCS 1 high byte first). Given the bytes of an identity
// READ from address 0, the table the servo speaks; nullopt when `bytes` do not tell (too short,
// another value, or a table without the flag).
inline constexpr std::uint8_t kByteOrderFlagAddress = 2;
std::optional<modbus_map::TableId> table_from_byte_order_flag(modbus_map::TableId assumed,
                                                              std::span<const std::uint8_t> bytes);
// The name Feetech gives a model number (FD tool, SDKs), or empty when not known.
std::string_view model_name(std::uint16_t model_number);

// Decode the bytes of one identity READ (layout.read.count bytes; fields beyond a shorter
// read stay empty).
ServoIdentity decode_identity(const IdentityLayout& layout, std::span<const std::uint8_t> bytes,
                              modbus_map::ByteOrder order);
std::optional<std::uint8_t> decode_response_level(const IdentityLayout& layout, std::span<const std::uint8_t> bytes);

// "8.42" (major.minor), "10760 (SM40BL)" (model number), "93" (one byte), "0x0101" (two-byte
// word), "-" for an absent value.
std::string format_identity_value(const IdentityLayout* layout, bool model, std::optional<std::uint16_t> value);

struct DiscoveredServo {
  std::uint8_t servo_id = 0;
  modbus_map::TableId table = modbus_map::TableId::Sts;
  bool online = false;
  std::uint8_t status = 0;  // ERROR byte of its PING answer
  ServoIdentity identity;
  std::string detail;  // why it is offline
};

struct DiscoveryReport {
  std::string bus_name;
  std::string device;
  std::string_view protocol;
  std::uint32_t baud = 0;
  std::span<const DiscoveredServo> servos;
};

// A header line and one line per servo, e.g.
//   bus arm: /dev/ttyUSB0, feetech at 1000000 bit/s, 5 of 6 servos online
//     servo   1  sts   online   model 10760 (SM40BL) firmware 2.48
//     servo   4  sts   OFFLINE  no answer to PING (3 attempts)
std::string format_discovery_summary(const DiscoveryReport& report);

}  // namespace sms::gateway
