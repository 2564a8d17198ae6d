#pragma once
// What a Modbus/TCP Security role may ask (docs/SECURITY.md, docs/DECISIONS.md
// "Operations and security"). Pure: no sockets, no Asio. The TLS listener puts a RoleGate in
// front of the same UnitRouter the plain listener uses, so every request that passes still goes
// through the safety rules; a refused request never reaches the router.
//
//   RolePolicy policy(config, catalog);  // one for the whole gateway, shared by every way in
//   if (const auto refusal = policy.refusal(Role::Operate, unit_id, pdu)) reply refusal->exception;
//
// Rights:
//   read      functions that only read (01 02 03 04, and 07 11 12 17 20 24 on passthrough units)
//   operate   also writes that change RAM: goals, speeds, torque on/off, acceleration, gains in
//             RAM, staged writes and ACTION, the gateway unit's coils (e-stop, re-arm), its
//             heartbeat registers and sync groups of RAM fields; the standard write functions
//             (05 06 15 16 22 23) on passthrough units
//   engineer  everything: EEPROM fields (ID, baud rate, limits, offsets, mode ...), the `lock`
//             field, mid-point calibration (torque field := 128, SMSMB fault-reset bit 2), sync
//             groups of EEPROM fields, and functions of unknown effect (08, 21, 43, vendor codes)
// Refusals: a function the role has no right to at all (read: every write; operate: functions
// of unknown effect) is 0x01 illegal function; a write function the role may use, aimed at an
// address it may not write (operate: an EEPROM field), is 0x02 illegal data address.
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/service/modbus_request.h"
#include "gateway/service/unit_catalog.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

struct RoleRefusal {
  ModbusException exception = ModbusException::IllegalFunction;  // 0x01 or 0x02
  std::string reason;                                            // for the log: "writes EEPROM field id (5)"
};

class RolePolicy {
 public:
  // The servo units' register maps come from `catalog`, which must outlive the policy.
  RolePolicy(const config::Config& config, const UnitCatalog& catalog);

  // nullopt: `role` may make the request (the router still decides everything else: unknown
  // units, malformed PDUs, read-only units and fields, the safety rules). A request the policy
  // cannot classify (malformed, an unknown unit, an address the map refuses anyway) is let
  // through to the router, which refuses it without writing.
  std::optional<RoleRefusal> refusal(config::Role role, std::uint8_t unit_id, std::span<const std::uint8_t> pdu) const;

 private:
  struct GroupBlock {
    std::uint16_t start = 0;
    std::uint16_t count = 0;
    std::string name;
    std::string field;
    bool engineer_only = false;
  };

  std::optional<RoleRefusal> servo_write_refusal(const modbus_map::RegisterMap& map,
                                                 std::span<const std::uint8_t> pdu) const;
  std::optional<RoleRefusal> gateway_write_refusal(std::span<const std::uint8_t> pdu) const;

  const UnitCatalog& catalog_;
  std::vector<GroupBlock> groups_;
};

// Whether a read-only unit answers `function` itself: nullopt when it may be served (reads),
// 0x02 for writes, as a write to a read-only field is answered (docs/PLC_GUIDE.md), 0x01 for
// functions whose effect the gateway cannot know (passthrough units forward any code; a
// read-only one forwards reads only). docs/DECISIONS.md "Operations and security". The unit
// router asks it for servo and passthrough units alike.
std::optional<ModbusException> read_only_refusal(std::uint8_t function);

// Whether writing `field` of a servo's table needs the engineer role whatever the value: EEPROM
// fields and the `lock` field (it only decides whether EEPROM writes persist).
bool engineer_only_field(const modbus_map::FieldSpec& field);

}  // namespace sms::gateway
