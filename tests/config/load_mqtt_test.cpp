// The mqtt section (MQTT Sparkplug B): defaults, every key, the dump that loads back the same,
// and each refusal's message and place.
#include <gtest/gtest.h>

#include <string>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;

const std::string kServos = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, name: shoulder}
  - {bus: arm, id: 2, table: sts}
)";

TEST(LoadMqtt, MinimalSectionGetsTheDefaults) {
  const auto config = load_config_string(kServos +
                                             "mqtt: {broker: \"127.0.0.1:1883\", group_id: plant, "
                                             "edge_node_id: gw1}\n",
                                         "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  ASSERT_TRUE(config->mqtt);
  const MqttConfig& mqtt = *config->mqtt;
  EXPECT_EQ(mqtt.broker, (HostPort{"127.0.0.1", 1883}));
  EXPECT_EQ(mqtt.client_id, "sms-gateway-gw1");
  EXPECT_EQ(mqtt.role, Role::Operate);
  EXPECT_EQ(mqtt.data_period, std::chrono::milliseconds{100});
  EXPECT_EQ(mqtt.report_period, std::chrono::seconds{0});
  EXPECT_EQ(mqtt.keepalive, std::chrono::seconds{30});
  EXPECT_FALSE(mqtt.tls);
  EXPECT_EQ(mqtt.primary_host_id, "");  // births follow the connection
  EXPECT_EQ(sparkplug_device_id(config->servos[0]), "shoulder");
  EXPECT_EQ(sparkplug_device_id(config->servos[1]), "unit-2");

  const auto without = load_config_string(kServos, "plant.yaml");
  ASSERT_TRUE(without);
  EXPECT_FALSE(without->mqtt);
  const auto disabled = load_config_string(kServos + "mqtt: {enabled: false, broker: nowhere}\n", "plant.yaml");
  ASSERT_TRUE(disabled) << disabled.error().to_string();
  EXPECT_FALSE(disabled->mqtt);
}

TEST(LoadMqtt, ReadsEveryKeyAndDumpsBackTheSame) {
  const auto config = load_config_string(kServos + R"(mqtt:
  broker: "broker.plant:8883"
  group_id: line-3
  edge_node_id: cell-7
  client_id: gw-cell-7
  username: gateway
  password_file: /etc/sms-gateway/mqtt.password
  tls: {ca: /etc/ssl/plant-ca.crt, certificate: /etc/sms-gateway/gw.crt, private_key: /etc/sms-gateway/gw.key}
  keepalive_s: 15
  role: engineer
  data_period_ms: 50
  report_period_s: 60
  deadband: {present_position: 2, present_load: 10}
  reconnect_min_ms: 200
  reconnect_max_ms: 10000
  primary_host_id: scada-1
)",
                                         "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  const MqttConfig& mqtt = *config->mqtt;
  EXPECT_EQ(mqtt.broker, (HostPort{"broker.plant", 8883}));
  EXPECT_EQ(mqtt.group_id, "line-3");
  EXPECT_EQ(mqtt.edge_node_id, "cell-7");
  EXPECT_EQ(mqtt.client_id, "gw-cell-7");
  EXPECT_EQ(mqtt.username, "gateway");
  EXPECT_EQ(mqtt.password_file, "/etc/sms-gateway/mqtt.password");
  ASSERT_TRUE(mqtt.tls);
  EXPECT_EQ(mqtt.tls->ca, "/etc/ssl/plant-ca.crt");
  EXPECT_EQ(mqtt.tls->certificate, "/etc/sms-gateway/gw.crt");
  EXPECT_EQ(mqtt.tls->private_key, "/etc/sms-gateway/gw.key");
  EXPECT_EQ(mqtt.keepalive, std::chrono::seconds{15});
  EXPECT_EQ(mqtt.role, Role::Engineer);
  EXPECT_EQ(mqtt.data_period, std::chrono::milliseconds{50});
  EXPECT_EQ(mqtt.report_period, std::chrono::seconds{60});
  ASSERT_EQ(mqtt.deadbands.size(), 2u);
  EXPECT_EQ(mqtt.deadbands[0], (MqttDeadband{"present_position", 2}));
  EXPECT_EQ(mqtt.deadbands[1], (MqttDeadband{"present_load", 10}));
  EXPECT_EQ(mqtt.reconnect_min, std::chrono::milliseconds{200});
  EXPECT_EQ(mqtt.reconnect_max, std::chrono::milliseconds{10000});
  EXPECT_EQ(mqtt.primary_host_id, "scada-1");

  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(*config);
  EXPECT_EQ(*again, *config);
}

TEST(LoadMqtt, RefusesWithPlaces) {
  const std::string head = kServos + "mqtt:\n  broker: \"127.0.0.1:1883\"\n";
  EXPECT_EQ(error_text(head + "  group_id: a/b\n  edge_node_id: gw\n"),
            "plant.yaml:8:13: mqtt.group_id: `a/b` cannot be a Sparkplug ID: it is an MQTT topic level, so no "
            "'/', '+' or '#'");
  EXPECT_EQ(error_text(head + "  group_id: g\n"), "plant.yaml:7:3: missing required key `edge_node_id` in mqtt");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  deadband: {present_postion: 2}\n"),
            "plant.yaml:10:14: mqtt.deadband: `present_postion` is not a field of any table (docs/REGISTER_MAP.md "
            "lists each table's fields)");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  password_file: /p\n"),
            "plant.yaml:10:18: mqtt.password_file: a password needs a username; add mqtt.username");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  tls: {ca: /ca, certificate: /c}\n"),
            "plant.yaml:10:8: mqtt.tls: certificate and private_key go together (a client certificate for the "
            "broker); give both or neither");
  EXPECT_EQ(
      error_text(head + "  group_id: g\n  edge_node_id: gw\n  reconnect_min_ms: 5000\n  reconnect_max_ms: 1000\n"),
      "plant.yaml:11:3: mqtt.reconnect_max_ms: 1000 is below reconnect_min_ms (5000)");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  role: admin\n"),
            "plant.yaml:10:9: mqtt.role: expected one of none, read, operate, engineer, got `admin`");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  last_will: x\n"),
            "plant.yaml:10:3: unknown key `last_will` in mqtt; allowed keys here: broker, group_id, edge_node_id, "
            "client_id, username, password_file, tls, keepalive_s, role, data_period_ms, report_period_s, "
            "deadband, reconnect_min_ms, reconnect_max_ms, enabled, primary_host_id");
  EXPECT_EQ(error_text(head + "  group_id: g\n  edge_node_id: gw\n  primary_host_id: \"scada/1\"\n"),
            "plant.yaml:10:20: mqtt.primary_host_id: `scada/1` cannot be a Sparkplug ID: it is an MQTT topic level, "
            "so no '/', '+' or '#'");
}

TEST(LoadMqtt, ServoNamesMustBeUniqueDeviceIds) {
  const std::string mqtt = "mqtt: {broker: \"127.0.0.1:1883\", group_id: g, edge_node_id: gw}\n";
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, name: "left/arm"}
)" + mqtt),
            "plant.yaml:4:5: servos[0].name: `left/arm` cannot be a Sparkplug device ID (mqtt is configured): no "
            "'/', '+' or '#'");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, name: unit-2}
  - {bus: arm, id: 2, table: sts}
)" + mqtt),
            "plant.yaml:5:5: servos[1].name: Sparkplug device ID `unit-2` is also servos[0]'s (line 4, column 5); "
            "names must be unique when mqtt is configured");
}

}  // namespace
}  // namespace sms::config
