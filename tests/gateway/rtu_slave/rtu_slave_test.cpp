// The upstream RTU port's pure parts: its silences (t1.5, t3.5) per rate and frame_gap, the units
// it serves, and its counters as Prometheus text. The port on a line is tested end to end in
// tests/e2e/rtu_slave_test.cpp.
#include <gtest/gtest.h>

#include <string>

#include "config/load.h"
#include "gateway/observability/metrics.h"
#include "gateway/rtu_slave/rtu_slave_port.h"
#include "tests/support/metrics_http_client.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

double micros(std::chrono::nanoseconds duration) { return std::chrono::duration<double, std::micro>(duration).count(); }

SerialSettings line(std::uint32_t baud, config::Parity parity = config::Parity::Even) {
  return SerialSettings{"/dev/null", baud, parity, 1};
}

TEST(RtuSlaveTiming, SpecIsThreeAndAHalfCharactersUpTo19200ThenFixed) {
  // 9600 8E1: 11 bits a character; 3.5 characters = 38.5 bit times = 4010.4 us.
  auto timing = rtu_slave_timing(line(9600), {});
  EXPECT_NEAR(micros(timing.t35), 4010.4, 1.0);
  EXPECT_NEAR(micros(timing.t15), 1718.75, 1.0);
  timing = rtu_slave_timing(line(19200, config::Parity::None), {});  // 10 bits: 1822.9 us
  EXPECT_NEAR(micros(timing.t35), 1822.9, 1.0);
  for (const std::uint32_t fast : {38400u, 115200u, 1000000u}) {
    timing = rtu_slave_timing(line(fast), {});
    EXPECT_EQ(timing.t35, 1750us) << fast;
    EXPECT_EQ(timing.t15, 750us) << fast;
  }
}

TEST(RtuSlaveTiming, OtherFrameGapsGiveT15AsThreeSevenths) {
  config::FrameGap characters;
  characters.kind = config::FrameGap::Kind::Characters;
  const auto timing = rtu_slave_timing(line(115200), characters);  // 38.5 bits at 115200: 334.2 us
  EXPECT_NEAR(micros(timing.t35), 334.2, 0.5);
  config::FrameGap fixed;
  fixed.kind = config::FrameGap::Kind::Fixed;
  fixed.fixed = 7000us;
  EXPECT_EQ(rtu_slave_timing(line(115200), fixed).t15, 3000us);
}

config::Config panel_config(const std::string& port) {
  auto config = config::load_config_string(R"(modbus_tcp: {gateway_unit_id: 247}
buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 3, bus: arm, id: 3, table: sts}
  - {unit: 1, bus: arm, id: 1, table: sts}
modbus_rtu_slave:
  - )" + port + "\n",
                                           "panel.yaml");
  if (!config) throw std::runtime_error(config.error().to_string());
  return std::move(*config);
}

TEST(RtuSlaveUnits, EveryConfiguredUnitAndTheGatewayUnitUnlessListed) {
  auto config = panel_config("{device: /dev/ttyUSB1}");
  EXPECT_EQ(served_units(config, config.modbus_rtu_slave[0]), (std::vector<std::uint8_t>{1, 3, 247}));
  config = panel_config("{device: /dev/ttyUSB1, units: [3]}");
  EXPECT_EQ(served_units(config, config.modbus_rtu_slave[0]), (std::vector<std::uint8_t>{3}));
}

TEST(RtuSlaveMetrics, EachPortIsLabelledByItsDevice) {
  MetricsSnapshot snapshot;
  RtuSlaveStats port;
  port.device = "/dev/ttyUSB1";
  port.open = true;
  port.requests = 10;
  port.answers = 8;
  port.broadcasts = 1;
  port.crc_errors = 2;
  port.dropped_frames = 3;
  port.silent_units = 4;
  port.role_refusals = 5;
  port.port_lost = 6;
  snapshot.rtu_slaves.push_back(port);
  port.device = "/dev/ttyUSB2";
  port.open = false;
  snapshot.rtu_slaves.push_back(port);
  const auto metrics = test::parse_exposition(render_prometheus(snapshot));
  EXPECT_TRUE(metrics.errors.empty()) << metrics.errors.front();
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_up{device="/dev/ttyUSB1"})"), "1");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_up{device="/dev/ttyUSB2"})"), "0");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_requests_total{device="/dev/ttyUSB1"})"), "10");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_answers_total{device="/dev/ttyUSB1"})"), "8");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_broadcasts_total{device="/dev/ttyUSB1"})"), "1");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_crc_errors_total{device="/dev/ttyUSB1"})"), "2");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_dropped_frames_total{device="/dev/ttyUSB1"})"), "3");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_silent_units_total{device="/dev/ttyUSB1"})"), "4");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_role_refusals_total{device="/dev/ttyUSB1"})"), "5");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_port_lost_total{device="/dev/ttyUSB2"})"), "6");
  EXPECT_EQ(metrics.count("sms_gateway_rtu_slave_requests_total"), 2u);
  // Without ports, no families.
  EXPECT_EQ(render_prometheus(MetricsSnapshot{}).find("rtu_slave"), std::string::npos);
}

}  // namespace
}  // namespace sms::gateway
