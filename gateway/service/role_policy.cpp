#include "gateway/service/role_policy.h"

#include <set>
#include <variant>

#include "gateway/service/modbus_request.h"
#include "modbus_map/tables.h"
#include "protocol/modbus_pdu.h"

namespace sms::gateway {
namespace {

using config::Role;
using protocol::function_effect;
using protocol::FunctionEffect;

// The torque switch of each table; 128 written to it is the mid-point calibration (docs/PROTOCOL.md §1.1).
bool is_torque_switch(const modbus_map::FieldSpec& field) {
  return field.name == "torque_enable" || field.name == "torque_switch";
}

// The standard Modbus write functions an operator may use on a passthrough unit.
bool standard_write(std::uint8_t function) {
  switch (function) {
    case 0x05:
    case 0x06:
    case 0x0F:
    case 0x10:
    case 0x16:
    case 0x17: return true;
    default: return false;
  }
}

std::string field_text(const modbus_map::FieldSpec& field) {
  return std::string(field.name) + " (" + std::to_string(field.addr) + ")";
}

}  // namespace

std::optional<ModbusException> read_only_refusal(std::uint8_t function) {
  switch (function_effect(function)) {
    case FunctionEffect::Reads: return std::nullopt;
    case FunctionEffect::Writes: return ModbusException::IllegalDataAddress;
    case FunctionEffect::Unknown: break;
  }
  return ModbusException::IllegalFunction;
}

bool engineer_only_field(const modbus_map::FieldSpec& field) {
  return field.area == modbus_map::Area::Eeprom || field.name == "lock";
}

RolePolicy::RolePolicy(const config::Config& config, const UnitCatalog& catalog) : catalog_(catalog) {
  for (const auto& group : config.sync_groups) {
    GroupBlock block{group.holding_register_start, group.register_count(), group.name, group.field, false};
    for (const std::uint8_t member : group.members) {
      const config::ServoConfig* servo = config::find_unit(config, member);
      if (servo == nullptr || servo->passthrough()) continue;
      const auto* field = modbus_map::field_by_name(modbus_map::table(*servo->table), group.field);
      if (field != nullptr && engineer_only_field(*field)) block.engineer_only = true;
    }
    groups_.push_back(std::move(block));
  }
}

std::optional<RoleRefusal> RolePolicy::refusal(Role role, std::uint8_t unit_id,
                                               std::span<const std::uint8_t> pdu) const {
  const std::uint8_t function = pdu.empty() ? 0 : pdu[0];
  const FunctionEffect effect = function_effect(function);
  switch (role) {
    case Role::Engineer: return std::nullopt;
    case Role::None: return RoleRefusal{ModbusException::IllegalFunction, "the connection has no role"};
    case Role::Read:
      if (effect == FunctionEffect::Reads) return std::nullopt;
      return RoleRefusal{ModbusException::IllegalFunction, "role read may only read"};
    case Role::Operate: break;
  }
  if (effect == FunctionEffect::Reads) return std::nullopt;
  if (effect == FunctionEffect::Unknown) {
    return RoleRefusal{ModbusException::IllegalFunction, "functions of unknown effect need role engineer"};
  }
  if (catalog_.passthrough(unit_id)) {
    if (standard_write(function)) return std::nullopt;
    return RoleRefusal{ModbusException::IllegalFunction,
                       "this write function needs role engineer on a passthrough unit"};
  }
  if (const CatalogUnit* unit = catalog_.servo(unit_id)) return servo_write_refusal(unit->map, pdu);
  if (unit_id == catalog_.gateway_unit_id()) return gateway_write_refusal(pdu);
  return std::nullopt;  // an unknown unit: the router answers 0x0A
}

std::optional<RoleRefusal> RolePolicy::servo_write_refusal(const modbus_map::RegisterMap& map,
                                                           std::span<const std::uint8_t> pdu) const {
  const auto request = parse_request(pdu);
  if (!request) return std::nullopt;  // the router answers the parse error, without writing
  std::optional<modbus_map::MapResult<modbus_map::WritePlan>> plan;
  if (const auto* bits = std::get_if<WriteBitsRequest>(&*request)) {
    plan = map.plan_coil_write(bits->address, bits->values);
  } else if (const auto* registers = std::get_if<WriteRegistersRequest>(&*request)) {
    plan = map.plan_register_write(registers->address, registers->values);
  } else if (const auto* both = std::get_if<ReadWriteRegistersRequest>(&*request)) {
    plan = map.plan_register_write(both->write.address, both->write.values);
  }
  if (!plan || !*plan) return std::nullopt;  // a read, or a write the map refuses anyway

  const modbus_map::TableSpec& table = map.servo_table();
  const std::size_t per_address = map.bytes_per_bus_address();
  const modbus_map::ByteOrder order =
      table.addressing == modbus_map::Addressing::Register ? modbus_map::ByteOrder::HighFirst : map.byte_order();
  for (const auto& write : (**plan).writes) {
    const std::size_t count = write.data.size() / per_address;
    std::set<const modbus_map::FieldSpec*> seen;
    for (std::size_t i = 0; i < count; ++i) {
      const auto* field = modbus_map::field_covering(table, static_cast<std::uint16_t>(write.address + i));
      if (field == nullptr || !seen.insert(field).second) continue;
      if (engineer_only_field(*field)) {
        return RoleRefusal{ModbusException::IllegalDataAddress,
                           "writes " + std::string(field->area == modbus_map::Area::Eeprom ? "EEPROM " : "") +
                               "field " + field_text(*field) + ", which needs role engineer"};
      }
      if (!is_torque_switch(*field) || field->addr < write.address) continue;
      const std::size_t offset = static_cast<std::size_t>(field->addr - write.address) * per_address;
      if (offset + field->size > write.data.size()) continue;
      const auto raw =
          modbus_map::load_raw(std::span<const std::uint8_t>(write.data).subspan(offset), field->size, order);
      if (raw == static_cast<std::uint32_t>(modbus_map::kCalibrateTorqueValue)) {
        return RoleRefusal{ModbusException::IllegalDataAddress,
                           "mid-point calibration (" + field_text(*field) + " := 128) needs role engineer"};
      }
    }
  }
  return std::nullopt;
}

std::optional<RoleRefusal> RolePolicy::gateway_write_refusal(std::span<const std::uint8_t> pdu) const {
  const auto request = parse_request(pdu);
  if (!request) return std::nullopt;
  const WriteRegistersRequest* write = std::get_if<WriteRegistersRequest>(&*request);
  if (const auto* both = std::get_if<ReadWriteRegistersRequest>(&*request)) write = &both->write;
  if (write == nullptr) return std::nullopt;  // coils: ACTION, e-stop, re-arm are an operator's
  const std::uint32_t first = write->address;
  const std::uint32_t end = first + write->values.size();
  for (const auto& group : groups_) {
    if (!group.engineer_only) continue;
    if (first < std::uint32_t{group.start} + group.count && group.start < end) {
      return RoleRefusal{ModbusException::IllegalDataAddress, "sync group " + group.name + " writes EEPROM field " +
                                                                  group.field + ", which needs role engineer"};
    }
  }
  return std::nullopt;
}

}  // namespace sms::gateway
