// Metrics from a running gateway: simulated servos on a real pty, the Gateway's own engines
// and TCP server, collect_metrics() behind a MetricsServer, scraped over a socket. Nothing is
// mocked; the values come from real bus traffic.
#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <thread>

#include "gateway/observability/metrics_server.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/simulated_gateway.h"

// Designated initializers leave the members a test does not name at their defaults, on purpose.
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using test::eventually;
using test::http_request;
using test::parse_exposition;
using testing::SimulatedGateway;

constexpr const char* kTwoServos = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: arm, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts, name: shoulder}
  - {unit: 12, bus: arm, id: 2, table: sts}
)";

double number(const test::Exposition& e, const std::string& key) {
  const std::string text = e.value(key);
  if (text == "(absent)") {
    ADD_FAILURE() << key << " is absent";
    return -1;
  }
  return std::stod(text);
}

class MetricsOfARunningGateway : public ::testing::Test {
 protected:
  MetricsOfARunningGateway() : plant_(testing::sts_bus(2), kTwoServos) {
    plant_.wait_until_polled(1);
    plant_.wait_until_polled(12);
    engines_.push_back(&plant_.gateway().engine(0));
    server_.emplace(MetricsServerOptions{.listen = {"127.0.0.1", 0}}, [this] {
      return collect_metrics(plant_.gateway().config(), engines_, plant_.gateway().server_stats(), traffic_, started_);
    });
    server_->start();
  }

  test::Exposition scrape() {
    const auto response = http_request(server_->port(), "GET", "/metrics");
    EXPECT_EQ(response.status, 200);
    auto exposition = parse_exposition(response.body);
    EXPECT_TRUE(exposition.errors.empty()) << ::testing::PrintToString(exposition.errors);
    return exposition;
  }

  const SteadyClock::time_point started_ = SteadyClock::now();
  SimulatedGateway plant_;
  std::vector<BusEngine*> engines_;
  ModbusTrafficCounters traffic_;
  std::optional<MetricsServer> server_;
};

TEST_F(MetricsOfARunningGateway, PollingShowsInBusAndServoCounters) {
  const auto e = scrape();
  const std::string arm = "{bus=\"arm\",protocol=\"feetech\"}";
  EXPECT_EQ(e.value("sms_gateway_bus_up" + arm), "1");
  EXPECT_EQ(e.value("sms_gateway_bus_servos" + arm), "2");
  EXPECT_EQ(e.value("sms_gateway_bus_servos_online" + arm), "2");
  EXPECT_GT(number(e, "sms_gateway_bus_frames_ok_total" + arm), 0);
  EXPECT_GT(number(e, "sms_gateway_bus_poll_cycles_total" + arm), 0);
  EXPECT_GT(number(e, "sms_gateway_bus_last_poll_cycle_seconds" + arm), 0);
  EXPECT_LT(number(e, "sms_gateway_bus_last_poll_cycle_seconds" + arm), 1);

  const std::string shoulder = "{bus=\"arm\",unit=\"1\",servo=\"1\",name=\"shoulder\"}";
  const std::string twelve = "{bus=\"arm\",unit=\"12\",servo=\"2\"}";
  for (const auto& servo : {shoulder, twelve}) {
    EXPECT_EQ(e.value("sms_gateway_servo_online" + servo), "1") << servo;
    EXPECT_GT(number(e, "sms_gateway_servo_replies_ok_total" + servo), 0) << servo;
    EXPECT_GE(number(e, "sms_gateway_servo_cache_age_seconds" + servo), 0) << servo;
    EXPECT_LT(number(e, "sms_gateway_servo_cache_age_seconds" + servo), 1) << servo;
  }
  // wait_until_polled() connected twice over Modbus TCP.
  EXPECT_GE(number(e, "sms_gateway_tcp_connections_accepted_total"), 2);
}

TEST_F(MetricsOfARunningGateway, CountersGrowBetweenScrapes) {
  const std::string key = "sms_gateway_bus_frames_ok_total{bus=\"arm\",protocol=\"feetech\"}";
  const double before = number(scrape(), key);
  EXPECT_TRUE(eventually([&] { return number(scrape(), key) > before; }));
}

TEST_F(MetricsOfARunningGateway, SilentServoGoesOfflineAndCountsTimeouts) {
  plant_.bus().set_offline(2, true);
  const std::string twelve = "{bus=\"arm\",unit=\"12\",servo=\"2\"}";
  EXPECT_TRUE(eventually([&] {
    const auto e = scrape();
    return e.value("sms_gateway_servo_online" + twelve) == "0" &&
           e.value("sms_gateway_bus_servos_online{bus=\"arm\",protocol=\"feetech\"}") == "1";
  }));
  const auto e = scrape();
  EXPECT_GT(number(e, "sms_gateway_servo_timeouts_total" + twelve), 0);
  EXPECT_GT(number(e, "sms_gateway_bus_timeouts_total{bus=\"arm\",protocol=\"feetech\"}"), 0);
  // Its data grows old instead of disappearing.
  EXPECT_GE(number(e, "sms_gateway_servo_cache_age_seconds" + twelve), 0);
}

TEST_F(MetricsOfARunningGateway, HealthzFollowsTheBus) {
  const auto up = http_request(server_->port(), "GET", "/healthz");
  EXPECT_EQ(up.status, 200);
  EXPECT_EQ(up.body, "ok\n");

  plant_.bus().stop();  // the pty goes away: the bus is down
  EXPECT_TRUE(eventually([&] { return http_request(server_->port(), "GET", "/healthz").status == 503; }));
  const auto down = http_request(server_->port(), "GET", "/healthz");
  EXPECT_EQ(down.body, "bus arm is down\n");
  EXPECT_EQ(scrape().value("sms_gateway_bus_up{bus=\"arm\",protocol=\"feetech\"}"), "0");
}

}  // namespace
}  // namespace sms::gateway
