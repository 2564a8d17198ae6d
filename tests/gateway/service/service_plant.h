#pragma once
// The plant the service tests share: a feetech bus with an sts unit (1), the same kind of servo in
// the smsmb profile (2) and an sms1 one high byte first (3); a modbus-rtu bus with a passthrough
// unit (10) and an smsmb servo (11); a sync group of a RAM field and one of an EEPROM field.
#include <cstdint>
#include <stdexcept>
#include <vector>

#include "config/load.h"
#include "gateway/service/role_policy.h"
#include "gateway/service/unit_catalog.h"

namespace sms::gateway::testing {

inline config::Config service_plant() {
  auto config = config::load_config_string(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: line, device: /dev/ttyUSB1, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sts, profile: smsmb}
  - {bus: arm, id: 3, table: sms1, byte_order: high-first}
  - {bus: line, id: 10, table: passthrough}
  - {bus: line, id: 11, table: smsmb}
sync_groups:
  - {name: goals, field: goal_position, members: [1], holding_register_start: 0}
  - {name: temperatures, field: max_temperature, members: [1], holding_register_start: 10}
)",
                                           "plant.yaml");
  if (!config) throw std::runtime_error(config.error().to_string());
  return *config;
}

// The plant's configuration with its catalog and the policy over them (each keeps references).
struct ServicePlant {
  config::Config config = service_plant();
  UnitCatalog catalog{config};
  RolePolicy policy{config, catalog};
};

// An FC06 PDU.
inline std::vector<std::uint8_t> write_register(std::uint16_t address, std::uint16_t value) {
  return {0x06, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)};
}

}  // namespace sms::gateway::testing
