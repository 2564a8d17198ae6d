// The rights of the Modbus/TCP Security roles (gateway/service/role_policy.h): what read, operate and
// engineer may ask of servo units, passthrough units and the gateway unit, and which exception
// a refusal is (0x01 for a function class the role lacks, 0x02 for an address it may not write).
#include <gtest/gtest.h>

#include "gateway/service/role_policy.h"
#include "tests/gateway/service/service_plant.h"

namespace sms::gateway {
namespace {

using config::Role;
using Pdu = std::vector<std::uint8_t>;
using testing::write_register;

std::optional<std::uint8_t> refused(const RolePolicy& policy, Role role, std::uint8_t unit, const Pdu& pdu) {
  const auto refusal = policy.refusal(role, unit, pdu);
  if (!refusal) return std::nullopt;
  return static_cast<std::uint8_t>(refusal->exception);
}

TEST(RolePolicy, ReadRoleReadsOnlyAndGetsIllegalFunctionForEveryWrite) {
  const testing::ServicePlant plant_;
  const RolePolicy& policy = plant_.policy;
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
  const testing::ServicePlant plant_;
  const RolePolicy& policy = plant_.policy;
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
  const testing::ServicePlant plant_;
  const RolePolicy& policy = plant_.policy;
  EXPECT_EQ(refused(policy, Role::Engineer, 1, write_register(5, 7)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 1, write_register(40, 128)), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 10, {0x08, 0x00, 0x01, 0x00, 0x00}), std::nullopt);
  EXPECT_EQ(refused(policy, Role::Engineer, 255, write_register(10, 75)), std::nullopt);
}

// What a read-only unit refuses, function by function (role_policy.h read_only_refusal).
std::string verdict(std::uint8_t function) {
  const auto refusal = read_only_refusal(function);
  if (!refusal) return "served";
  return "exception " + std::to_string(static_cast<int>(*refusal));
}

TEST(ReadOnlyUnit, ReadsAreServed) {
  EXPECT_EQ(verdict(0x01), "served");  // read coils
  EXPECT_EQ(verdict(0x02), "served");  // read discrete inputs
  EXPECT_EQ(verdict(0x03), "served");  // read holding registers
  EXPECT_EQ(verdict(0x04), "served");  // read input registers
  EXPECT_EQ(verdict(0x11), "served");  // report server ID (passthrough units)
}

TEST(ReadOnlyUnit, WritesAreRefusedWith02LikeAReadOnlyField) {
  EXPECT_EQ(verdict(0x05), "exception 2");  // write single coil
  EXPECT_EQ(verdict(0x06), "exception 2");  // write single register
  EXPECT_EQ(verdict(0x0F), "exception 2");  // write multiple coils
  EXPECT_EQ(verdict(0x10), "exception 2");  // write multiple registers
  EXPECT_EQ(verdict(0x16), "exception 2");  // mask write register
  EXPECT_EQ(verdict(0x17), "exception 2");  // read/write multiple registers: it writes
  EXPECT_EQ(verdict(0x15), "exception 2");  // write file record
}

TEST(ReadOnlyUnit, FunctionsOfUnknownEffectAreRefusedWith01) {
  EXPECT_EQ(verdict(0x08), "exception 1");  // diagnostics (sub-function 01 restarts)
  EXPECT_EQ(verdict(0x2B), "exception 1");  // encapsulated interface transport
  EXPECT_EQ(verdict(0x41), "exception 1");  // user-defined (Feetech's restart on SMSMB)
  EXPECT_EQ(verdict(0x64), "exception 1");
  EXPECT_EQ(verdict(0x00), "exception 1");
}

}  // namespace
}  // namespace sms::gateway
