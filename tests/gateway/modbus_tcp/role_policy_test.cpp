// The rights of the Modbus/TCP Security roles (gateway/modbus_tcp/role_policy.h): what read, operate and
// engineer may ask of servo units, passthrough units and the gateway unit, and which exception
// a refusal is (0x01 for a function class the role lacks, 0x02 for an address it may not write).
#include <gtest/gtest.h>

#include "config/load.h"
#include "gateway/modbus_tcp/role_policy.h"
#include "gateway/modbus_tcp/tls.h"

namespace sms::gateway {
namespace {

using config::Role;
using Pdu = std::vector<std::uint8_t>;

config::Config plant() {
  auto config = config::load_config_string(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: line, device: /dev/ttyUSB1, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sts, profile: smsmb}
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

Pdu write_register(std::uint16_t address, std::uint16_t value) {
  return {0x06, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)};
}

std::optional<std::uint8_t> refused(const RolePolicy& policy, Role role, std::uint8_t unit, const Pdu& pdu) {
  const auto refusal = policy.refusal(role, unit, pdu);
  if (!refusal) return std::nullopt;
  return exception_code(refusal->fault);
}

TEST(RolePolicy, ReadRoleReadsOnlyAndGetsIllegalFunctionForEveryWrite) {
  const RolePolicy policy(plant());
  EXPECT_EQ(refused(policy, Role::Read, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Read, 1, {0x04, 0x00, 0x38, 0x00, 0x01}), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Read, 1, write_register(42, 2048)), 0x01);
  EXPECT_EQ(refused(policy, Role::Read, 1, {0x05, 0x00, 0x28, 0x00, 0x00}), 0x01);    // torque off too
  EXPECT_EQ(refused(policy, Role::Read, 255, {0x05, 0x00, 0x01, 0xFF, 0x00}), 0x01);  // the e-stop coil
  EXPECT_EQ(refused(policy, Role::Read, 10, {0x08, 0x00, 0x01, 0x00, 0x00}), 0x01);
  EXPECT_EQ(refused(policy, Role::Read, 10, {0x11}), std::nullopt);  // report server id only reads
  EXPECT_EQ(refused(policy, Role::None, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}), 0x01);
}

TEST(RolePolicy, OperateWritesRamButNotEepromLockOrCalibration) {
  const RolePolicy policy(plant());
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(42, 2048)), std::nullopt);        // goal
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(40, 1)), std::nullopt);           // torque on
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(512 + 42, 2048)), std::nullopt);  // staged goal
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(13, 75)), 0x02);   // max_temperature (EEPROM)
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(5, 7)), 0x02);     // id
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(6, 0)), 0x02);     // baud_rate
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(55, 0)), 0x02);    // lock
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(40, 128)), 0x02);  // mid-point calibration
  // FC16 over goal acceleration .. goal position: RAM only.
  EXPECT_EQ(refused(policy, Role::Operate, 1, {0x10, 0x00, 0x29, 0x00, 0x02, 0x04, 0x00, 0x0A, 0x08, 0x00}),
            std::nullopt);
  // smsmb profile of an sts servo, and an smsmb servo: ID register 0x0A is EEPROM.
  EXPECT_EQ(refused(policy, Role::Operate, 2, write_register(0x0A, 7)), 0x02);
  EXPECT_EQ(refused(policy, Role::Operate, 2, write_register(0x86, 1u << 2)), 0x02);  // fault reset: calibration
  EXPECT_EQ(refused(policy, Role::Operate, 2, write_register(0x80, 2048)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Operate, 11, write_register(0x0A, 7)), 0x02);
  EXPECT_EQ(refused(policy, Role::Operate, 11, write_register(0x80, 2048)), std::nullopt);
  // Passthrough: standard writes yes, functions of unknown effect no.
  EXPECT_EQ(refused(policy, Role::Operate, 10, write_register(100, 1)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Operate, 10, {0x08, 0x00, 0x01, 0x00, 0x00}), 0x01);
  EXPECT_EQ(refused(policy, Role::Operate, 10, {0x41}), 0x01);
  // Gateway unit: coils and sync groups of RAM fields yes, of EEPROM fields no.
  EXPECT_EQ(refused(policy, Role::Operate, 255, {0x05, 0x00, 0x01, 0xFF, 0x00}), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Operate, 255, write_register(0, 2048)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Operate, 255, write_register(10, 75)), 0x02);
  // What the router refuses anyway is left to it (no write happens either way).
  EXPECT_EQ(refused(policy, Role::Operate, 1, write_register(200, 1)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Operate, 77, write_register(13, 75)), std::nullopt);
}

TEST(RolePolicy, EngineerMayDoEverything) {
  const RolePolicy policy(plant());
  EXPECT_EQ(refused(policy, Role::Engineer, 1, write_register(5, 7)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 1, write_register(40, 128)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 10, {0x08, 0x00, 0x01, 0x00, 0x00}), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 255, write_register(10, 75)), std::nullopt);
}

// Which role a client certificate gets (tls.h role_for): the role extension when it names a
// role or a role_names entry; another scheme's name falls back to the CN/SAN mapping, then
// default_role, as if the certificate had no extension.
TEST(RoleFor, ExtensionRoleNamesThenCnOrSanThenDefault) {
  config::TlsConfig tls;
  tls.roles = {{"plc-3", Role::Operate}, {"hmi-2.plant", Role::Read}};
  tls.role_names = {{"Engineer", Role::Engineer}, {"Guest", Role::None}};
  const auto role_of = [&](std::optional<std::string> extension, std::string cn, std::vector<std::string> sans = {}) {
    return role_for(tls, PeerCertificate{"CN=" + cn, cn, std::move(sans), std::move(extension)});
  };
  EXPECT_EQ(role_of("read", "plc-3").role, Role::Read);  // the extension wins over the CN mapping
  EXPECT_EQ(role_of("read", "plc-3").source, "role extension");
  EXPECT_EQ(role_of("none", "plc-3").role, Role::None);  // the issuer said: no rights
  EXPECT_EQ(role_of("Engineer", "nobody").role, Role::Engineer);
  EXPECT_EQ(role_of("Engineer", "nobody").source, "role extension `Engineer` (role_names)");
  EXPECT_EQ(role_of("Guest", "plc-3").role, Role::None);  // role_names says none: refused, not mapped by CN
  const RoleDecision operator_by_cn = role_of("Operator", "plc-3");
  EXPECT_EQ(operator_by_cn.role, Role::Operate);
  EXPECT_EQ(operator_by_cn.source, "role extension `Operator` not in role_names, so roles[plc-3] (CN)");
  EXPECT_EQ(role_of("Operator", "panel", {"hmi-2.plant"}).role, Role::Read);  // by subjectAltName
  EXPECT_EQ(role_of(std::nullopt, "plc-3").role, Role::Operate);
  // Not mapped: refused, unless default_role gives one.
  const RoleDecision stranger = role_of("Operator", "stranger");
  EXPECT_EQ(stranger.role, Role::None);
  EXPECT_NE(stranger.source.find("`Operator`, which is not read, operate, engineer nor in modbus_tcp.tls.role_names"),
            std::string::npos)
      << stranger.source;
  tls.default_role = Role::Read;
  EXPECT_EQ(role_of("Operator", "stranger").role, Role::Read);
  EXPECT_EQ(role_of("Operator", "stranger").source, "role extension `Operator` not in role_names, so default_role");
  EXPECT_EQ(role_of(std::nullopt, "stranger").role, Role::Read);
  EXPECT_EQ(role_of("none", "stranger").role, Role::None);  // default_role does not override an explicit none
}

}  // namespace
}  // namespace sms::gateway
