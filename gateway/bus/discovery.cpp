#include "gateway/bus/discovery.h"

#include <fmt/format.h>

#include <algorithm>

#include "modbus_map/tables.h"

namespace sms::gateway {

const IdentityLayout* identity_layout(modbus_map::TableId table) {
  const auto found = std::find_if(kIdentityLayouts.begin(), kIdentityLayouts.end(),
                                  [table](const IdentityLayout& layout) { return layout.table == table; });
  return found == kIdentityLayouts.end() ? nullptr : &*found;
}

std::optional<modbus_map::TableId> table_from_byte_order_flag(modbus_map::TableId assumed,
                                                              std::span<const std::uint8_t> bytes) {
  using modbus_map::TableId;
  if (assumed != TableId::Sts && assumed != TableId::Scs) return std::nullopt;
  if (bytes.size() <= kByteOrderFlagAddress) return std::nullopt;
  switch (bytes[kByteOrderFlagAddress]) {
    case 0: return TableId::Sts;
    case 1: return TableId::Scs;
    default: return std::nullopt;
  }
}

std::string_view model_name(std::uint16_t model_number) {
  // Model numbers as the SDKs read addresses 3-4 (LeRobot's Feetech MODEL_NUMBER_TABLE; the
  // SM40BL readout "8.42" of doc 001 §15 is 10760 read as one word).
  struct KnownModel {
    std::uint16_t number;
    std::string_view name;
  };
  static constexpr KnownModel kKnownModels[] = {
      {777, "STS3215"}, {2825, "STS3250"}, {10760, "SM40BL"}, {11272, "SM8512BL"}, {1284, "SCS0009"},
  };
  for (const KnownModel& model : kKnownModels) {
    if (model.number == model_number) return model.name;
  }
  return {};
}

namespace {

std::optional<std::uint16_t> decode_field(const std::optional<IdentityField>& field,
                                          std::span<const std::uint8_t> bytes, modbus_map::ByteOrder order) {
  if (!field || field->offset + field->size > bytes.size()) return std::nullopt;
  const auto value = bytes.subspan(field->offset, field->size);
  if (field->format == IdentityFormat::MajorMinor && field->size == 2) {
    return static_cast<std::uint16_t>(value[0] << 8 | value[1]);
  }
  return static_cast<std::uint16_t>(modbus_map::load_raw(value, field->size, order));
}

}  // namespace

ServoIdentity decode_identity(const IdentityLayout& layout, std::span<const std::uint8_t> bytes,
                              modbus_map::ByteOrder order) {
  return {decode_field(layout.model, bytes, order), decode_field(layout.firmware, bytes, order)};
}

std::optional<std::uint8_t> decode_response_level(const IdentityLayout& layout, std::span<const std::uint8_t> bytes) {
  if (!layout.response_level_offset || *layout.response_level_offset >= bytes.size()) return std::nullopt;
  return bytes[*layout.response_level_offset];
}

std::string format_identity_value(const IdentityLayout* layout, bool model, std::optional<std::uint16_t> value) {
  if (!value) return "-";
  const std::optional<IdentityField> field =
      layout == nullptr ? std::nullopt : (model ? layout->model : layout->firmware);
  if (field && field->format == IdentityFormat::MajorMinor) return fmt::format("{}.{}", *value >> 8, *value & 0xFF);
  if (field && field->format == IdentityFormat::ModelNumber) {
    const std::string_view name = model_name(*value);
    return name.empty() ? fmt::format("{}", *value) : fmt::format("{} ({})", *value, name);
  }
  // A two-byte version word reads best in hex (sms1 V1.01 is 0x0101).
  if (field && field->size == 2) return fmt::format("0x{:04X}", *value);
  return fmt::format("{}", *value);
}

std::string format_discovery_summary(const DiscoveryReport& report) {
  const auto online = std::count_if(report.servos.begin(), report.servos.end(),
                                    [](const DiscoveredServo& servo) { return servo.online; });
  std::string text = fmt::format("bus {}: {}, {} at {} bit/s, {} of {} servos online", report.bus_name, report.device,
                                 report.protocol, report.baud, online, report.servos.size());
  for (const auto& servo : report.servos) {
    const auto& table = modbus_map::table(servo.table);
    const IdentityLayout* layout = identity_layout(servo.table);
    if (servo.online) {
      text += fmt::format("\n  servo {:>3}  {:<5} online   model {:<6} firmware {:<6} status 0x{:02X}", servo.servo_id,
                          table.name, format_identity_value(layout, true, servo.identity.model),
                          format_identity_value(layout, false, servo.identity.firmware), servo.status);
    } else {
      text += fmt::format("\n  servo {:>3}  {:<5} OFFLINE  {}", servo.servo_id, table.name, servo.detail);
    }
  }
  return text;
}

}  // namespace sms::gateway
