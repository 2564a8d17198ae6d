// The environment overlay (config/env.h): each variable replaces one setting, invalid values are
// refused with the variable's name and the valid form, and the configuration is then unchanged.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdlib>
#include <map>
#include <string>

#include "config/env.h"
#include "config/load.h"

namespace sms::config {
namespace {

using namespace std::chrono_literals;

using Variables = std::map<std::string, std::string, std::less<>>;

EnvLookup lookup_in(const Variables& variables) {
  return [&variables](std::string_view name) -> std::optional<std::string> {
    const auto found = variables.find(name);
    if (found == variables.end()) return std::nullopt;
    return found->second;
  };
}

Config file_config() {
  auto config = load_config_string(R"(modbus_tcp:
  listen: 127.0.0.1:5020
  max_connections: 8
  idle_timeout_s: 30
  allow: [10.0.0.0/8]
buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
logging:
  level: info
  metrics_listen: 127.0.0.1:9102
)",
                                   "plant.yaml");
  if (!config) throw std::runtime_error(config.error().to_string());
  return std::move(*config);
}

std::string error_of(const Variables& variables) {
  Config config = file_config();
  const auto applied = apply_environment(config, lookup_in(variables));
  if (applied) return "(accepted)";
  return applied.error();
}

TEST(ConfigEnv, NoVariablesLeaveTheConfigurationAsItWas) {
  Config config = file_config();
  const auto applied = apply_environment(config, lookup_in({}));
  ASSERT_TRUE(applied) << applied.error();
  EXPECT_TRUE(applied->empty());
  EXPECT_EQ(config, file_config());
}

TEST(ConfigEnv, EveryVariableReplacesItsSetting) {
  const Variables variables{
      {"SMS_GATEWAY_LISTEN", "0.0.0.0:502"}, {"SMS_GATEWAY_MAX_CONNECTIONS", "200"},
      {"SMS_GATEWAY_IDLE_TIMEOUT_S", "0"},   {"SMS_GATEWAY_ALLOW", "192.168.10.0/24, fd00::/8,10.1.2.3"},
      {"SMS_GATEWAY_LOG_LEVEL", "debug"},    {"SMS_GATEWAY_LOG_FORMAT", "json"},
      {"SMS_GATEWAY_METRICS", "[::]:9102"},
  };
  Config config = file_config();
  const auto applied = apply_environment(config, lookup_in(variables));
  ASSERT_TRUE(applied) << applied.error();

  EXPECT_EQ(*applied,
            (std::vector<std::string>{"SMS_GATEWAY_LISTEN", "SMS_GATEWAY_MAX_CONNECTIONS", "SMS_GATEWAY_IDLE_TIMEOUT_S",
                                      "SMS_GATEWAY_ALLOW", "SMS_GATEWAY_LOG_LEVEL", "SMS_GATEWAY_LOG_FORMAT",
                                      "SMS_GATEWAY_METRICS"}));
  EXPECT_EQ(config.modbus_tcp.listen, (HostPort{"0.0.0.0", 502}));
  EXPECT_EQ(config.modbus_tcp.max_connections, 200u);
  EXPECT_EQ(config.modbus_tcp.idle_timeout, 0s);
  ASSERT_EQ(config.modbus_tcp.allow.size(), 3u);
  EXPECT_EQ(config.modbus_tcp.allow[0].to_string(), "192.168.10.0/24");
  EXPECT_EQ(config.modbus_tcp.allow[1].to_string(), "fd00::/8");
  EXPECT_EQ(config.modbus_tcp.allow[2].to_string(), "10.1.2.3/32");
  EXPECT_EQ(config.logging.level, LogLevel::Debug);
  EXPECT_EQ(config.logging.format, LogFormat::Json);
  EXPECT_EQ(config.logging.metrics_listen, (HostPort{"::", 9102}));
  // What no variable names stays as the file says.
  EXPECT_EQ(config.modbus_tcp.gateway_unit_id, 255);
  EXPECT_EQ(config.buses, file_config().buses);
}

TEST(ConfigEnv, EmptyOrBlankVariableCountsAsNotSet) {
  Config config = file_config();
  const auto applied = apply_environment(config, lookup_in({{"SMS_GATEWAY_ALLOW", ""}, {"SMS_GATEWAY_LISTEN", "  "}}));
  ASSERT_TRUE(applied) << applied.error();
  EXPECT_TRUE(applied->empty());
  EXPECT_EQ(config, file_config());
}

TEST(ConfigEnv, MetricsOffTurnsTheEndpointOff) {
  Config config = file_config();
  ASSERT_TRUE(apply_environment(config, lookup_in({{"SMS_GATEWAY_METRICS", "off"}})));
  EXPECT_FALSE(config.logging.metrics_listen);
}

TEST(ConfigEnv, InvalidValuesNameTheVariableAndTheValidForm) {
  EXPECT_EQ(error_of({{"SMS_GATEWAY_LISTEN", "502"}}),
            "SMS_GATEWAY_LISTEN=\"502\": \"502\" is not HOST:PORT (e.g. 0.0.0.0:502); expected HOST:PORT (e.g. "
            "0.0.0.0:502, \"[::]:502\") (replaces modbus_tcp.listen)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_MAX_CONNECTIONS", "0"}}),
            "SMS_GATEWAY_MAX_CONNECTIONS=\"0\": 0 is outside 1..4096; expected a whole number 1..4096 (replaces "
            "modbus_tcp.max_connections)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_MAX_CONNECTIONS", "12abc"}}),
            "SMS_GATEWAY_MAX_CONNECTIONS=\"12abc\": not a whole number 1..4096; expected a whole number 1..4096 "
            "(replaces modbus_tcp.max_connections)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_IDLE_TIMEOUT_S", "-1"}}),
            "SMS_GATEWAY_IDLE_TIMEOUT_S=\"-1\": -1 is outside 0..86400; expected seconds 0..86400 (0: never close "
            "idle clients) (replaces modbus_tcp.idle_timeout_s)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_LOG_LEVEL", "verbose"}}),
            "SMS_GATEWAY_LOG_LEVEL=\"verbose\": not one of trace, debug, info, warn, error, critical, off; expected "
            "trace, debug, info, warn, error, critical or off (replaces logging.level)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_LOG_FORMAT", "JSON"}}),
            "SMS_GATEWAY_LOG_FORMAT=\"JSON\": not one of plain, json; expected plain or json (replaces "
            "logging.format)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_METRICS", "localhost"}}),
            "SMS_GATEWAY_METRICS=\"localhost\": \"localhost\" is not HOST:PORT (e.g. 0.0.0.0:502); expected "
            "HOST:PORT (e.g. 0.0.0.0:9102), or off (replaces logging.metrics_listen)");
}

TEST(ConfigEnv, AllowListErrorsSayWhichItem) {
  EXPECT_EQ(error_of({{"SMS_GATEWAY_ALLOW", "10.0.0.0/8,192.168.1.300"}}),
            "SMS_GATEWAY_ALLOW=\"10.0.0.0/8,192.168.1.300\": item 2: \"192.168.1.300\" is not an IPv4 or IPv6 "
            "address; write ADDRESS/PREFIX (e.g. 192.168.10.0/24, fd00::/8) or one address (10.0.0.7, ::1); expected "
            "a comma-separated list of addresses or CIDR networks (e.g. 192.168.10.0/24,fd00::/8) (replaces "
            "modbus_tcp.allow)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_ALLOW", "10.0.0.0/8,,10.1.0.0/16"}}),
            "SMS_GATEWAY_ALLOW=\"10.0.0.0/8,,10.1.0.0/16\": item 2 is empty; expected a comma-separated list of "
            "addresses or CIDR networks (e.g. 192.168.10.0/24,fd00::/8) (replaces modbus_tcp.allow)");
  EXPECT_EQ(error_of({{"SMS_GATEWAY_ALLOW", "10.0.0.1/8"}}),
            "SMS_GATEWAY_ALLOW=\"10.0.0.1/8\": item 1: \"10.0.0.1/8\" has address bits set below its /8 prefix; the "
            "network is 10.0.0.0/8 (or give /32 for the one address); expected a comma-separated list of addresses "
            "or CIDR networks (e.g. 192.168.10.0/24,fd00::/8) (replaces modbus_tcp.allow)");
}

TEST(ConfigEnv, OneInvalidVariableLeavesEveryOtherSettingUnchanged) {
  Config config = file_config();
  const auto applied =
      apply_environment(config, lookup_in({{"SMS_GATEWAY_LISTEN", "0.0.0.0:502"}, {"SMS_GATEWAY_LOG_FORMAT", "xml"}}));
  ASSERT_FALSE(applied);
  EXPECT_EQ(config, file_config());
}

TEST(ConfigEnv, ProcessEnvironmentIsRead) {
  ASSERT_EQ(::setenv("SMS_GATEWAY_LOG_FORMAT", "json", 1), 0);
  Config config = file_config();
  const auto applied = apply_environment(config);
  ::unsetenv("SMS_GATEWAY_LOG_FORMAT");
  ASSERT_TRUE(applied) << applied.error();
  EXPECT_EQ(config.logging.format, LogFormat::Json);
}

TEST(ConfigEnv, TableListsEveryVariableOnce) {
  std::vector<std::string_view> names;
  for (const auto& variable : environment_variables()) {
    EXPECT_TRUE(variable.name.starts_with("SMS_GATEWAY_")) << variable.name;
    EXPECT_EQ(std::count(names.begin(), names.end(), variable.name), 0) << variable.name;
    names.push_back(variable.name);
  }
  EXPECT_EQ(names.size(), 7u);
}

}  // namespace
}  // namespace sms::config
