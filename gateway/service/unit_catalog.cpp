#include "gateway/service/unit_catalog.h"

#include <stdexcept>
#include <string>

namespace sms::gateway {

modbus_map::Profile map_profile(config::Profile profile) {
  return profile == config::Profile::Smsmb ? modbus_map::Profile::Smsmb : modbus_map::Profile::Native;
}

Expected<modbus_map::BusRange> poll_block_of(const config::BusConfig& bus, const config::ServoConfig& servo) {
  const modbus_map::TableId table = *servo.table;
  if (bus.poll.range) return modbus_map::BusRange{bus.poll.range->start, bus.poll.range->count};
  if (!bus.poll.fields.empty()) {
    auto fields = modbus_map::poll_block_for_fields(table, bus.poll.fields);
    if (!fields) return unexpected("bus '" + bus.name + "': poll_fields: " + fields.error());
    return *fields;
  }
  return modbus_map::default_poll_block(table);
}

UnitCatalog::UnitCatalog(const config::Config& config) : gateway_unit_id_(config.modbus_tcp.gateway_unit_id) {
  for (const auto& servo : config.servos) {
    if (servo.passthrough()) {
      passthrough_[servo.unit_id] = true;
      continue;
    }
    auto map = modbus_map::RegisterMap::create(*servo.table, map_profile(servo.profile), servo.byte_order);
    if (!map) throw std::invalid_argument("unit " + std::to_string(servo.unit_id) + ": " + map.error());
    std::optional<modbus_map::RegisterMap> native;
    if (map->profile() != modbus_map::Profile::Native) {
      auto own = modbus_map::RegisterMap::create(*servo.table, modbus_map::Profile::Native, servo.byte_order);
      if (!own) throw std::invalid_argument("unit " + std::to_string(servo.unit_id) + ": " + own.error());
      native = std::move(*own);
    }
    units_[servo.unit_id] =
        std::make_unique<const CatalogUnit>(CatalogUnit{&servo, std::move(*map), std::move(native)});
  }
}

}  // namespace sms::gateway
