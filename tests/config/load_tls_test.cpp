// modbus_tcp.plain and modbus_tcp.tls (Modbus/TCP Security): defaults, every rejection's message
// and place, and the dump that loads back to the same configuration.
#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <string_view>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;
using testing::kBusAndServo;

const std::string kTls = R"(modbus_tcp:
  listen: "0.0.0.0:502"
  plain: false
  tls:
    listen: "0.0.0.0:802"
    certificate: /etc/sms-gateway/tls/gateway.crt
    private_key: /etc/sms-gateway/tls/gateway.key
    ca: /etc/sms-gateway/tls/plant-ca.crt
    roles: {plc-1: operate, hmi-1.plant: read, laptop-eng: engineer}
    default_role: none
    role_names: {Operator: operate, Engineer: engineer, Guest: none}
    handshake_timeout_ms: 1500
    max_handshakes: 8
    max_handshakes_per_address: 2
)";

TEST(LoadTls, DefaultsArePlainOnlyAndNoTls) {
  const auto config = load_config_string(kBusAndServo, "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  EXPECT_TRUE(config->modbus_tcp.plain);
  EXPECT_FALSE(config->modbus_tcp.tls);
}

TEST(LoadTls, ReadsEveryKeyAndDumpsBackTheSame) {
  const auto config = load_config_string(kTls + kBusAndServo, "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  EXPECT_FALSE(config->modbus_tcp.plain);
  ASSERT_TRUE(config->modbus_tcp.tls);
  const TlsConfig& tls = *config->modbus_tcp.tls;
  EXPECT_EQ(tls.listen, (HostPort{"0.0.0.0", 802}));
  EXPECT_EQ(tls.certificate, "/etc/sms-gateway/tls/gateway.crt");
  EXPECT_EQ(tls.private_key, "/etc/sms-gateway/tls/gateway.key");
  EXPECT_EQ(tls.ca, "/etc/sms-gateway/tls/plant-ca.crt");
  ASSERT_EQ(tls.roles.size(), 3u);
  EXPECT_EQ(tls.roles[0], (TlsRoleMapping{"plc-1", Role::Operate}));
  EXPECT_EQ(tls.roles[1], (TlsRoleMapping{"hmi-1.plant", Role::Read}));
  EXPECT_EQ(tls.roles[2], (TlsRoleMapping{"laptop-eng", Role::Engineer}));
  EXPECT_EQ(tls.default_role, Role::None);
  ASSERT_EQ(tls.role_names.size(), 3u);
  EXPECT_EQ(tls.role_names[0], (TlsRoleMapping{"Operator", Role::Operate}));
  EXPECT_EQ(tls.role_names[1], (TlsRoleMapping{"Engineer", Role::Engineer}));
  EXPECT_EQ(tls.role_names[2], (TlsRoleMapping{"Guest", Role::None}));
  EXPECT_EQ(tls.handshake_timeout, std::chrono::milliseconds{1500});
  EXPECT_EQ(tls.max_handshakes, 8u);
  EXPECT_EQ(tls.max_handshakes_per_address, 2u);

  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(*config);
  EXPECT_EQ(*again, *config);
}

TEST(LoadTls, HandshakeBudgetDefaults) {
  const std::string minimal = "modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c}\n";
  const auto config = load_config_string(minimal + kBusAndServo, "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  const TlsConfig& tls = *config->modbus_tcp.tls;
  EXPECT_EQ(tls.handshake_timeout, std::chrono::milliseconds{3000});
  EXPECT_EQ(tls.max_handshakes, 16u);
  EXPECT_EQ(tls.max_handshakes_per_address, 4u);
  EXPECT_TRUE(tls.role_names.empty());
  // A listener budget below the per-address default lowers the per-address one with it.
  const auto small = load_config_string(
      "modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, max_handshakes: 2}\n" +
          kBusAndServo,
      "plant.yaml");
  ASSERT_TRUE(small) << small.error().to_string();
  EXPECT_EQ(small->modbus_tcp.tls->max_handshakes_per_address, 2u);
}

TEST(LoadTls, RefusesWithPlaces) {
  EXPECT_EQ(error_text("modbus_tcp: {plain: false}\n" + kBusAndServo),
            "plant.yaml:1:21: modbus_tcp.plain: false leaves the gateway without a listener; configure "
            "modbus_tcp.tls (Modbus/TCP Security) or remove the key");
  EXPECT_EQ(
      error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b}\n" + kBusAndServo),
      "plant.yaml:2:8: missing required key `ca` in modbus_tcp.tls");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "roles: {plc-1: admin}}\n" +
                       kBusAndServo),
            "plant.yaml:2:86: modbus_tcp.tls.roles.plc-1: expected one of none, read, operate, engineer, got `admin`");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "roles: {plc-1: read, plc-1: operate}}\n" +
                       kBusAndServo),
            "plant.yaml:2:92: modbus_tcp.tls.roles: `plc-1` is given twice (first at line 2, column 79)");
  EXPECT_EQ(error_text("modbus_tcp:\n  listen: \"0.0.0.0:802\"\n  tls: {listen: \"0.0.0.0:802\", certificate: a, "
                       "private_key: b, ca: c}\n" +
                       kBusAndServo),
            "plant.yaml:3:3: modbus_tcp.tls.listen: 0.0.0.0:802 is also modbus_tcp.listen (plain Modbus TCP); give "
            "TLS its own port (802 is Modbus/TCP Security's) or set plain: false");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "default_role: admin}\n" +
                       kBusAndServo),
            "plant.yaml:2:85: modbus_tcp.tls.default_role: expected one of none, read, operate, engineer, got `admin`");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "role_names: {read: operate}}\n" +
                       kBusAndServo),
            "plant.yaml:2:84: modbus_tcp.tls.role_names: `read` already is a role; list only other names here");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "role_names: {Operator: admin}}\n" +
                       kBusAndServo),
            "plant.yaml:2:94: modbus_tcp.tls.role_names.Operator: expected one of none, read, operate, engineer, got "
            "`admin`");
  EXPECT_EQ(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "max_handshakes: 4, max_handshakes_per_address: 5}\n" +
                       kBusAndServo),
            "plant.yaml:2:90: modbus_tcp.tls.max_handshakes_per_address: 5 is more than max_handshakes (4); lower it "
            "or raise max_handshakes");
  EXPECT_NE(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: a, private_key: b, ca: c, "
                       "handshake_timeout_ms: 50}\n" +
                       kBusAndServo)
                .find("modbus_tcp.tls.handshake_timeout_ms"),
            std::string::npos);
  EXPECT_NE(error_text("modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificat: a}\n" + kBusAndServo)
                .find("unknown key `certificat` in modbus_tcp.tls (did you mean `certificate`?)"),
            std::string::npos);
}

}  // namespace
}  // namespace sms::config
