// Which role a client certificate gets (gateway/modbus_tcp/tls.h role_for): the role extension
// when it names a role or a role_names entry; another scheme's name falls back to the CN/SAN
// mapping, then default_role, as if the certificate had no extension.
#include <gtest/gtest.h>

#include "gateway/modbus_tcp/tls.h"

namespace sms::gateway {
namespace {

using config::Role;

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
