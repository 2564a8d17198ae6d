#pragma once
// Every configured servo unit's register map, built once at start and shared by whoever needs
// one: the unit router (its servo units), the gateway unit (sync groups' value rules), the role
// policy, and through the router's servo units the console and the Sparkplug node. One place
// turns a unit's configuration (table, profile, byte order) into its map. Pure: no buses.
//
//   const UnitCatalog catalog(config);  // throws std::invalid_argument naming the unit
//   if (const CatalogUnit* unit = catalog.servo(3)) unit->map.plan_register_write(42, values);
#include <array>
#include <cstdint>
#include <memory>
#include <optional>

#include "config/config.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

// The register map profile a unit's `profile` names.
modbus_map::Profile map_profile(config::Profile profile);

// The block the bus's poll cycle reads from a table servo (bus addresses): the bus's `poll`
// range, else the smallest block holding its poll fields, else the table's feedback block. A
// servo unit's input registers serve this block only. The error names the bus.
Expected<modbus_map::BusRange> poll_block_of(const config::BusConfig& bus, const config::ServoConfig& servo);

struct CatalogUnit {
  const config::ServoConfig* servo = nullptr;  // its configuration
  // What the unit's Modbus addresses name: its table, in its profile and byte order.
  modbus_map::RegisterMap map;
  // The table's own map where `map` shows another profile (smsmb): the value rules of the field
  // a sync group writes, which is the servo's field, not an SMSMB register.
  std::optional<modbus_map::RegisterMap> native;

  const modbus_map::RegisterMap& native_map() const { return native ? *native : map; }
};

class UnitCatalog {
 public:
  // Throws std::invalid_argument "unit N: why" for a table and profile without a register map
  // (the configuration loader refuses those first). `config` must outlive the catalog.
  explicit UnitCatalog(const config::Config& config);

  // The servo unit with a control table `unit_id` is, or nullptr (passthrough, the gateway
  // unit, no unit).
  const CatalogUnit* servo(std::uint8_t unit_id) const { return units_[unit_id].get(); }
  bool passthrough(std::uint8_t unit_id) const { return passthrough_[unit_id]; }
  std::uint8_t gateway_unit_id() const { return gateway_unit_id_; }

 private:
  std::array<std::unique_ptr<const CatalogUnit>, 256> units_{};
  std::array<bool, 256> passthrough_{};
  std::uint8_t gateway_unit_id_ = 255;
};

}  // namespace sms::gateway
