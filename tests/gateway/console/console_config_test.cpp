// The console section of the configuration (docs/CONSOLE.md "Configuration").
#include <gtest/gtest.h>

#include "config/load.h"

namespace sms::config {
namespace {

constexpr const char* kBase =
    "buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}\n"
    "servos:\n  - {bus: arm, id: 1, table: sts}\n";
constexpr const char* kHash = "\"$argon2id$v=19$m=65536,t=2,p=1$c29tZXNhbHQ$aGFzaA\"";

TEST(ConsoleConfig, LoadsUsersAndRoundTrips) {
  const auto config = load_config_string(std::string(kBase) +
                                             "console:\n  listen: 0.0.0.0:8443\n"
                                             "  certificate: /etc/sms-gateway/console/console.crt\n"
                                             "  key: /etc/sms-gateway/console/console.key\n  users:\n"
                                             "    - {name: alice, role: engineer, password_hash: " +
                                             kHash + "}\n",
                                         "c.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  ASSERT_TRUE(config->console);
  EXPECT_EQ(config->console->listen.to_string(), "0.0.0.0:8443");
  ASSERT_EQ(config->console->users.size(), 1u);
  EXPECT_EQ(config->console->users[0].role, Role::Engineer);
  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string();
  EXPECT_EQ(*again, *config);
}

TEST(ConsoleConfig, ErrorsSayWhatToDo) {
  struct Case {
    std::string yaml;
    std::string message;
  };
  const Case cases[] = {
      {"console: {listen: 0.0.0.0:8080}\n", "reachable from other machines"},
      {"console: {tls: true}\n", "needs modbus_tcp.tls"},
      {"console: {users: [{name: a, role: read, password_hash: hunter2}]}\n", "not a password hash"},
      {"console: {users: [{name: a, role: none, password_hash: " + std::string(kHash) + "}]}\n", "role none"},
      {"console: {users: [{name: a, role: read, password_hash: " + std::string(kHash) +
           "}, {name: a, role: read, password_hash: " + kHash + "}]}\n",
       "already"},
      {"console: {users: [{name: 'a b', role: read, password_hash: " + std::string(kHash) + "}]}\n", "letters, digits"},
      {"console: {listn: 1}\n", "did you mean `listen`"},
  };
  for (const auto& c : cases) {
    const auto config = load_config_string(std::string(kBase) + c.yaml, "c.yaml");
    ASSERT_FALSE(config) << c.yaml;
    EXPECT_NE(config.error().to_string().find(c.message), std::string::npos) << config.error().to_string();
  }
}

}  // namespace
}  // namespace sms::config
