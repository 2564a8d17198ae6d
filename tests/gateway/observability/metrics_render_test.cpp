// Rendering the gateway's counters as Prometheus text: real counter objects (BusCounters,
// PollCache, ModbusTrafficCounters) filled by the test, the text checked sample by sample
// against values written out by hand, and the exposition format checked line by line.
#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <vector>

#include "config/load.h"
#include "gateway/observability/metrics.h"
#include "tests/support/metrics_http_client.h"

// Designated initializers leave the members a test does not name at their defaults, on purpose.
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using test::parse_exposition;

config::Config two_bus_config() {
  auto config = config::load_config_string(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts, name: "Achse \"1\""}
  - {unit: 17, bus: arm, id: 7, table: sts}
  - {unit: 30, bus: base, id: 3, table: d55d}
)",
                                           "metrics.yaml");
  if (!config) throw std::runtime_error(config.error().to_string());
  return std::move(*config);
}

std::vector<std::uint8_t> pdu(std::initializer_list<std::uint8_t> bytes) { return bytes; }

// Two buses: arm up with servo 1 polled 250 ms ago and servo 7 never answering; base down.
class MetricsRender : public ::testing::Test {
 protected:
  MetricsRender()
      : arm_cache_(std::vector<PollCache::ServoEntry>{{1, {56, 15}}, {7, {56, 15}}}),
        base_cache_(std::vector<PollCache::ServoEntry>{{3, {36, 8}}}) {
    arm_cache_.store_block(1, std::vector<std::uint8_t>(15, 0), now_ - 250ms);
    arm_cache_.counters(1)->replies_ok = 1234;
    arm_cache_.counters(1)->timeouts = 5;
    arm_cache_.counters(1)->last_status = 0x20;
    arm_cache_.set_online(7, false);
    arm_cache_.counters(7)->timeouts = 9;

    arm_counters_.frames_ok = 1000;
    arm_counters_.timeouts = 12;
    arm_counters_.checksum_errors = 3;
    arm_counters_.stray_frames = 4;
    arm_counters_.discarded_bytes = 77;
    arm_counters_.retries = 8;
    arm_counters_.transactions = 1500;
    arm_counters_.queue_full = 6;
    arm_counters_.bus_down_events = 1;
    arm_counters_.poll_cycles = 480;
    arm_counters_.last_poll_cycle_us = 1500;

    base_counters_.bus_down_events = 2;

    for (int i = 0; i < 4; ++i) traffic_.count_request(pdu({0x03, 0x00, 0x38, 0x00, 0x02}));
    traffic_.count_request(pdu({0x10, 0x00, 0x2A, 0x00, 0x01, 0x02, 0x07, 0xD0}));
    traffic_.count_request(pdu({0x10, 0x00, 0x2A, 0x00, 0x01, 0x02, 0x07, 0xD0}));
    traffic_.count_request(pdu({0x41}));
    traffic_.count_request(pdu({}));  // not a request: not counted
    for (int i = 0; i < 5; ++i) traffic_.count_response(pdu({0x03, 0x04, 0x00, 0x01, 0x00, 0x02}));
    traffic_.count_response(pdu({0x83, 0x02}));
    traffic_.count_response(pdu({0x90, 0x0B}));
    traffic_.count_response(pdu({0xC1, 0x01}));
    traffic_.count_response(pdu({0x83, 0x0C}));  // a code outside the standard table
  }

  MetricsSnapshot snapshot() const {
    MetricsSnapshot snapshot;
    snapshot.version = "1.2.3";
    snapshot.uptime = 3600s;
    snapshot.buses.push_back(read_bus_metrics(config_, 0, true, arm_counters_.snapshot(), arm_cache_, now_));
    snapshot.buses.push_back(read_bus_metrics(config_, 1, false, base_counters_.snapshot(), base_cache_, now_));
    snapshot.tcp = TcpServerStats{.open_connections = 3,
                                  .accepted = 40,
                                  .refused = 2,
                                  .denied = 2,
                                  .requests = 7,
                                  .bad_headers = 1,
                                  .idle_closed = 5,
                                  .refusals = {{{.max_connections = 2, .allow = 2}, {}}}};
    snapshot.traffic = traffic_.snapshot();
    return snapshot;
  }

  const SteadyClock::time_point now_ = SteadyClock::now();
  const config::Config config_ = two_bus_config();
  PollCache arm_cache_;
  PollCache base_cache_;
  BusCounters arm_counters_;
  BusCounters base_counters_;
  ModbusTrafficCounters traffic_;
};

TEST_F(MetricsRender, TextIsValidExpositionFormat) {
  const std::string text = render_prometheus(snapshot());
  const auto exposition = parse_exposition(text);
  EXPECT_TRUE(exposition.errors.empty()) << ::testing::PrintToString(exposition.errors) << "\n" << text;
  EXPECT_EQ(text.find("\n\n"), std::string::npos);
}

TEST_F(MetricsRender, FamilyHeaderIsHelpThenTypeThenSamples) {
  const std::string text = render_prometheus(snapshot());
  EXPECT_NE(text.find("# HELP sms_gateway_bus_up 1 when the bus's serial port is open, 0 while it is down (Modbus "
                      "0x0A)\n"
                      "# TYPE sms_gateway_bus_up gauge\n"
                      "sms_gateway_bus_up{bus=\"arm\",protocol=\"feetech\"} 1\n"
                      "sms_gateway_bus_up{bus=\"base\",protocol=\"d55d\"} 0\n"
                      "# HELP "),
            std::string::npos)
      << text;
  EXPECT_EQ(text.rfind("# HELP sms_gateway_build_info ", 0), 0u) << text;
}

TEST_F(MetricsRender, BusCountersCarryTheirValues) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  const std::string arm = "{bus=\"arm\",protocol=\"feetech\"}";
  EXPECT_EQ(e.value("sms_gateway_bus_frames_ok_total" + arm), "1000");
  EXPECT_EQ(e.value("sms_gateway_bus_timeouts_total" + arm), "12");
  EXPECT_EQ(e.value("sms_gateway_bus_checksum_errors_total" + arm), "3");
  EXPECT_EQ(e.value("sms_gateway_bus_stray_frames_total" + arm), "4");
  EXPECT_EQ(e.value("sms_gateway_bus_discarded_bytes_total" + arm), "77");
  EXPECT_EQ(e.value("sms_gateway_bus_retries_total" + arm), "8");
  EXPECT_EQ(e.value("sms_gateway_bus_transactions_total" + arm), "1500");
  EXPECT_EQ(e.value("sms_gateway_bus_queue_full_total" + arm), "6");
  EXPECT_EQ(e.value("sms_gateway_bus_down_events_total" + arm), "1");
  EXPECT_EQ(e.value("sms_gateway_bus_poll_cycles_total" + arm), "480");
  EXPECT_EQ(e.value("sms_gateway_bus_last_poll_cycle_seconds" + arm), "0.0015");
  EXPECT_EQ(e.value("sms_gateway_bus_servos" + arm), "2");
  EXPECT_EQ(e.value("sms_gateway_bus_servos_online" + arm), "1");

  const std::string base = "{bus=\"base\",protocol=\"d55d\"}";
  EXPECT_EQ(e.value("sms_gateway_bus_down_events_total" + base), "2");
  EXPECT_EQ(e.value("sms_gateway_bus_frames_ok_total" + base), "0");
  EXPECT_EQ(e.value("sms_gateway_bus_servos_online" + base), "0");
  EXPECT_EQ(e.types.at("sms_gateway_bus_frames_ok_total"), "counter");
  EXPECT_EQ(e.types.at("sms_gateway_bus_last_poll_cycle_seconds"), "gauge");
}

TEST_F(MetricsRender, ServoSamplesAreLabelledByBusUnitServoAndName) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  const std::string one = "{bus=\"arm\",unit=\"1\",servo=\"1\",name=\"Achse \\\"1\\\"\"}";
  EXPECT_EQ(e.value("sms_gateway_servo_online" + one), "1");
  EXPECT_EQ(e.value("sms_gateway_servo_replies_ok_total" + one), "1234");
  EXPECT_EQ(e.value("sms_gateway_servo_timeouts_total" + one), "5");
  EXPECT_EQ(e.value("sms_gateway_servo_last_status" + one), "32");
  EXPECT_EQ(e.value("sms_gateway_servo_cache_age_seconds" + one), "0.25");

  // Unit 17 (servo 7) never answered: no cache age at all, rather than a made-up one.
  const std::string seventeen = "{bus=\"arm\",unit=\"17\",servo=\"7\"}";
  EXPECT_EQ(e.value("sms_gateway_servo_online" + seventeen), "0");
  EXPECT_EQ(e.value("sms_gateway_servo_timeouts_total" + seventeen), "9");
  EXPECT_FALSE(e.has("sms_gateway_servo_cache_age_seconds" + seventeen));

  const std::string thirty = "{bus=\"base\",unit=\"30\",servo=\"3\"}";
  EXPECT_EQ(e.value("sms_gateway_servo_online" + thirty), "0");
  EXPECT_EQ(e.count("sms_gateway_servo_online"), 3u);
  EXPECT_EQ(e.count("sms_gateway_servo_cache_age_seconds"), 1u);
}

TEST_F(MetricsRender, TcpConnectionCounters) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  EXPECT_EQ(e.value("sms_gateway_tcp_connections"), "3");
  EXPECT_EQ(e.value("sms_gateway_tcp_connections_accepted_total"), "40");
  EXPECT_EQ(e.value("sms_gateway_tcp_connections_refused_total{listener=\"plain\",reason=\"max_connections\"}"), "2");
  EXPECT_EQ(e.value("sms_gateway_tcp_connections_refused_total{listener=\"plain\",reason=\"allow\"}"), "2");
  // Without modbus_tcp.tls there is no TLS listener to count.
  EXPECT_EQ(e.count("sms_gateway_tcp_connections_refused_total"), 2u);
  EXPECT_EQ(e.value("sms_gateway_tcp_connections_closed_idle_total"), "5");
  EXPECT_EQ(e.value("sms_gateway_tcp_bad_headers_total"), "1");
  EXPECT_EQ(e.types.at("sms_gateway_tcp_connections"), "gauge");
}

TEST_F(MetricsRender, ConsoleLoginFamiliesOnlyWithTheConsole) {
  auto with = snapshot();
  EXPECT_EQ(render_prometheus(with).find("sms_gateway_console_"), std::string::npos);
  with.console_logins = ConsoleLoginMetrics{2, 40, 300, 7, 3, 1};
  const auto e = parse_exposition(render_prometheus(with));
  EXPECT_EQ(e.value("sms_gateway_console_logins_total{result=\"ok\"}"), "2");
  EXPECT_EQ(e.value("sms_gateway_console_logins_total{result=\"failed\"}"), "40");
  EXPECT_EQ(e.value("sms_gateway_console_logins_total{result=\"throttled\"}"), "300");
  EXPECT_EQ(e.value("sms_gateway_console_logins_total{result=\"busy\"}"), "7");
  EXPECT_EQ(e.value("sms_gateway_console_login_waits{scope=\"address\"}"), "3");
  EXPECT_EQ(e.value("sms_gateway_console_login_waits{scope=\"user\"}"), "1");
  EXPECT_EQ(e.types.at("sms_gateway_console_logins_total"), "counter");
  EXPECT_EQ(e.types.at("sms_gateway_console_login_waits"), "gauge");
}

TEST_F(MetricsRender, MqttFamiliesOnlyWithMqtt) {
  auto with = snapshot();
  EXPECT_EQ(render_prometheus(with).find("sms_gateway_mqtt_"), std::string::npos);
  SparkplugStats mqtt;
  mqtt.link.connected = true;
  mqtt.link.connects = 3;
  mqtt.link.connect_failures = 7;
  mqtt.link.disconnects = 2;
  mqtt.link.publish_failures = 4;
  mqtt.published[0] = 3;    // NBIRTH
  mqtt.published[2] = 12;   // DBIRTH
  mqtt.published[5] = 900;  // DDATA
  mqtt.commands_ok = 11;
  mqtt.commands_refused = 5;
  mqtt.bad_messages = 1;
  mqtt.devices_online = 6;
  with.mqtt = mqtt;
  const auto e = parse_exposition(render_prometheus(with));
  EXPECT_EQ(e.value("sms_gateway_mqtt_connected"), "1");
  EXPECT_EQ(e.value("sms_gateway_mqtt_sessions_total{event=\"connected\"}"), "3");
  EXPECT_EQ(e.value("sms_gateway_mqtt_sessions_total{event=\"failed\"}"), "7");
  EXPECT_EQ(e.value("sms_gateway_mqtt_sessions_total{event=\"lost\"}"), "2");
  EXPECT_EQ(e.value("sms_gateway_mqtt_messages_published_total{type=\"NBIRTH\"}"), "3");
  EXPECT_EQ(e.value("sms_gateway_mqtt_messages_published_total{type=\"DBIRTH\"}"), "12");
  EXPECT_EQ(e.value("sms_gateway_mqtt_messages_published_total{type=\"DDATA\"}"), "900");
  EXPECT_EQ(e.value("sms_gateway_mqtt_messages_published_total{type=\"NDEATH\"}"), "0");
  EXPECT_EQ(e.value("sms_gateway_mqtt_publish_failures_total"), "4");
  EXPECT_EQ(e.value("sms_gateway_mqtt_commands_total{result=\"ok\"}"), "11");
  EXPECT_EQ(e.value("sms_gateway_mqtt_commands_total{result=\"refused\"}"), "5");
  EXPECT_EQ(e.value("sms_gateway_mqtt_bad_messages_total"), "1");
  EXPECT_EQ(e.value("sms_gateway_mqtt_devices_online"), "6");
  EXPECT_EQ(e.types.at("sms_gateway_mqtt_sessions_total"), "counter");
}

TEST_F(MetricsRender, RequestsByFunctionShowTheContractsFunctionsEvenAtZero) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  EXPECT_EQ(e.value("sms_gateway_modbus_requests_total{function=\"3\",name=\"read_holding_registers\"}"), "4");
  EXPECT_EQ(e.value("sms_gateway_modbus_requests_total{function=\"16\",name=\"write_multiple_registers\"}"), "2");
  EXPECT_EQ(e.value("sms_gateway_modbus_requests_total{function=\"65\",name=\"unknown\"}"), "1");
  EXPECT_EQ(e.value("sms_gateway_modbus_requests_total{function=\"5\",name=\"write_single_coil\"}"), "0");
  EXPECT_EQ(e.value("sms_gateway_modbus_requests_total{function=\"23\",name=\"read_write_multiple_registers\"}"), "0");
  // 01 02 03 04 05 06 15 16 23 always, plus 65 which was seen.
  EXPECT_EQ(e.count("sms_gateway_modbus_requests_total"), 10u);
  EXPECT_FALSE(e.has("sms_gateway_modbus_requests_total{function=\"7\",name=\"read_exception_status\"}"));
  EXPECT_FALSE(e.has("sms_gateway_modbus_requests_total{function=\"0\",name=\"unknown\"}"));
}

TEST_F(MetricsRender, ResponsesAndExceptionsByCode) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  EXPECT_EQ(e.value("sms_gateway_modbus_responses_total"), "9");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x01\",name=\"illegal_function\"}"), "1");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x02\",name=\"illegal_data_address\"}"), "1");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x0B\",name=\"gateway_target_device_failed_to_"
                    "respond\"}"),
            "1");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x0C\",name=\"unknown\"}"), "1");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x06\",name=\"server_device_busy\"}"), "0");
  EXPECT_EQ(e.value("sms_gateway_modbus_exceptions_total{code=\"0x0A\",name=\"gateway_path_unavailable\"}"), "0");
  // 01 02 03 04 06 0A 0B always, plus 0C which was seen.
  EXPECT_EQ(e.count("sms_gateway_modbus_exceptions_total"), 8u);
}

TEST_F(MetricsRender, BuildInfoAndUptime) {
  const auto e = parse_exposition(render_prometheus(snapshot()));
  EXPECT_EQ(e.value("sms_gateway_build_info{version=\"1.2.3\"}"), "1");
  EXPECT_EQ(e.value("sms_gateway_uptime_seconds"), "3600");
}

TEST(MetricsRenderEscaping, LabelValuesEscapeBackslashQuoteAndNewline) {
  MetricsSnapshot snapshot;
  BusMetrics bus;
  bus.name = "arm";
  bus.protocol = "feetech";
  bus.servos.push_back(ServoMetrics{.unit_id = 2, .servo_id = 2, .name = "C:\\axis \"2\"\nleft"});
  snapshot.buses.push_back(bus);
  const std::string text = render_prometheus(snapshot);
  EXPECT_NE(
      text.find(
          "sms_gateway_servo_online{bus=\"arm\",unit=\"2\",servo=\"2\",name=\"C:\\\\axis \\\"2\\\"\\nleft\"} 0\n"),
      std::string::npos)
      << text;
  EXPECT_TRUE(parse_exposition(text).errors.empty());
}

TEST(ModbusTrafficCounters, CountsFunctionCodesAndExceptionCodes) {
  ModbusTrafficCounters traffic;
  traffic.count_request(pdu({0x04, 0x03, 0xE8, 0x00, 0x08}));
  traffic.count_request(pdu({0x04, 0x03, 0xE8, 0x00, 0x08}));
  traffic.count_response(pdu({0x84, 0x0A}));
  traffic.count_response(pdu({0x04, 0x02, 0x00, 0x00}));
  traffic.count_response(pdu({0x84}));  // too short to be an exception answer
  const ModbusTrafficSnapshot snapshot = traffic.snapshot();
  EXPECT_EQ(snapshot.requests_by_function[0x04], 2u);
  EXPECT_EQ(snapshot.responses, 3u);
  EXPECT_EQ(snapshot.exceptions_by_code[0x0A], 1u);
  std::uint64_t exceptions = 0;
  for (const auto count : snapshot.exceptions_by_code) exceptions += count;
  EXPECT_EQ(exceptions, 1u);
}

TEST(MetricsHealth, HealthyWhenEveryBusIsUp) {
  MetricsSnapshot snapshot;
  snapshot.buses.push_back(BusMetrics{.name = "arm", .up = true});
  snapshot.buses.push_back(BusMetrics{.name = "base", .up = true});
  const Health health = health_of(snapshot);
  EXPECT_TRUE(health.ok);
  EXPECT_EQ(health.reason, "ok");
}

TEST(MetricsHealth, UnhealthyNamesEveryBusThatIsDown) {
  MetricsSnapshot snapshot;
  snapshot.buses.push_back(BusMetrics{.name = "arm", .up = false});
  snapshot.buses.push_back(BusMetrics{.name = "lift", .up = true});
  snapshot.buses.push_back(BusMetrics{.name = "base", .up = false});
  const Health health = health_of(snapshot);
  EXPECT_FALSE(health.ok);
  EXPECT_EQ(health.reason, "bus arm is down; bus base is down");
}

}  // namespace
}  // namespace sms::gateway
