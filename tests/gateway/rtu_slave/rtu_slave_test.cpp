// The upstream RTU port's pure parts: its silences (t1.5, t3.5) per rate and frame_gap, its echo
// window, the units it serves, and its counters as Prometheus text. In-process on a pty, with the
// whole gateway over a simulated bus: a PLC writing an unchanged value every cycle, an adapter
// that echoes, and a panel whose port's role may only read (the role gate every way in passes). The port against
// outside masters is tested end to end in tests/e2e/rtu_slave_test.cpp.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <stdlib.h>
#include <unistd.h>

#include <atomic>
#include <string>
#include <thread>

#include "config/load.h"
#include "gateway/observability/metrics.h"
#include "gateway/rtu_slave/rtu_slave_port.h"
#include "protocol/instructions.h"
#include "protocol/modbus_rtu.h"
#include "tests/support/bus_test_support.h"
#include "tests/support/echoing_adapter.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/simulated_gateway.h"

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

TEST(RtuEchoWindow, AutoEndsBeforeAMasterCouldRepeatTheFrameOnGivesALateAdapterTimeOffHasNone) {
  const auto timing = rtu_slave_timing(line(115200), {});  // t3.5 1750 us
  const auto fc06 = wire_time(line(115200), 8);            // 8 bytes x 11 bits: 764 us
  EXPECT_NEAR(micros(fc06), 763.9, 1.0);
  // A master hears the answer's last byte, keeps t3.5 and sends the same 8 bytes: the earliest
  // its request can end is t3.5 + 764 us after the answer; the 1 ms is the adapter's USB frame.
  EXPECT_EQ(rtu_echo_window(config::RtuEcho::Auto, timing, fc06), timing.t35 + fc06 + 1ms);
  EXPECT_EQ(rtu_echo_window(config::RtuEcho::On, timing, fc06), timing.t35 + fc06 + 50ms);
  EXPECT_EQ(rtu_echo_window(config::RtuEcho::Off, timing, fc06), std::nullopt);
  // Far below a PLC's cycle at every rate: 9600 bit/s, 4.0 ms + 9.2 ms + 1 ms.
  const auto slow = rtu_echo_window(config::RtuEcho::Auto, rtu_slave_timing(line(9600), {}), wire_time(line(9600), 8));
  ASSERT_TRUE(slow);
  EXPECT_LT(*slow, 15ms);
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
  port.echoes = 7;
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
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_echoes_total{device="/dev/ttyUSB1"})"), "7");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_silent_units_total{device="/dev/ttyUSB1"})"), "4");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_role_refusals_total{device="/dev/ttyUSB1"})"), "5");
  EXPECT_EQ(metrics.value(R"(sms_gateway_rtu_slave_port_lost_total{device="/dev/ttyUSB2"})"), "6");
  EXPECT_EQ(metrics.count("sms_gateway_rtu_slave_requests_total"), 2u);
  // Without ports, no families.
  EXPECT_EQ(render_prometheus(MetricsSnapshot{}).find("rtu_slave"), std::string::npos);
}

// The PLC's end of its RS-485 line: a pty whose other end the port (or an adapter) opens. It asks
// as a PLC does: sends a request and takes what comes within its response timeout.
class PlcLine {
 public:
  PlcLine() {
    fd_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (fd_ < 0 || ::grantpt(fd_) != 0 || ::unlockpt(fd_) != 0) throw std::runtime_error("no pty for the PLC");
    path_ = ::ptsname(fd_);
  }
  ~PlcLine() { ::close(fd_); }
  PlcLine(const PlcLine&) = delete;
  PlcLine& operator=(const PlcLine&) = delete;
  const std::string& path() const { return path_; }

  // Sends `request`; the answer is what comes within `timeout`, up to `expected` bytes.
  protocol::Bytes ask(const protocol::Bytes& request, std::size_t expected, std::chrono::milliseconds timeout = 1s) {
    if (::write(fd_, request.data(), request.size()) != static_cast<ssize_t>(request.size())) {
      throw std::runtime_error("the PLC could not write its request");
    }
    return read_for(timeout, expected);
  }
  // What came unasked within `wait`: a second answer, an echo answered as if it were a request.
  protocol::Bytes unasked(std::chrono::milliseconds wait) { return read_for(wait, SIZE_MAX); }

 private:
  protocol::Bytes read_for(std::chrono::milliseconds wait, std::size_t most) {
    protocol::Bytes got;
    const auto deadline = std::chrono::steady_clock::now() + wait;
    while (got.size() < most) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      pollfd fd{fd_, POLLIN, 0};
      if (left.count() <= 0 || ::poll(&fd, 1, static_cast<int>(left.count())) <= 0) break;
      std::array<std::uint8_t, 256> buffer{};
      const ssize_t n = ::read(fd_, buffer.data(), std::min(buffer.size(), most - got.size()));
      if (n <= 0) break;
      got.insert(got.end(), buffer.begin(), buffer.begin() + n);
    }
    return got;
  }

  int fd_ = -1;
  std::string path_;
};

// One sts servo (unit 1) behind the gateway, and one upstream port whose `modbus_rtu_slave` entry
// is `port` with "@PLC@" for its device.
constexpr const char* kPanelGateway = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: arm, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
modbus_rtu_slave:
  - )";

class CyclicWrites : public ::testing::Test {
 protected:
  // The gateway with its port on the PLC's line, or on an adapter that echoes (between the port
  // and the PLC's line) when `echoing`; the simulator counts each goal write that reaches servo 1.
  void start(const std::string& port, bool echoing = false) {
    if (echoing) adapter_ = std::make_unique<test::EchoingAdapter>(plc_.path(), 115200);
    std::string yaml = std::string(kPanelGateway) + port + "\n";
    yaml.replace(yaml.find("@PLC@"), 5, echoing ? adapter_->host_path() : plc_.path());
    gateway_ = std::make_unique<testing::SimulatedGateway>(testing::sts_bus(1), yaml);
    gateway_->bus().set_frame_observer([this](const simulator::ReceivedFrame& frame) {
      if (frame.id == 1 && frame.code == protocol::common::kWrite && !frame.params.empty() && frame.params[0] == 42) {
        ++goal_writes_;
      }
    });
    gateway_->wait_until_polled(1);
    ASSERT_TRUE(test::eventually([&] { return stats().open; }, "the upstream port open"));
  }
  RtuSlaveStats stats() const { return gateway_->gateway().metrics().rtu_slaves.at(0); }

  // A PLC's cycle: FC06 goal position (holding 42) := `goal` to unit 1, `writes` times, each
  // `pause` after the answer to the one before. Returns how many were answered, each with the
  // request byte for byte and within the PLC's 1 s response timeout.
  int write_unchanged_goal(std::uint16_t goal, int writes, std::chrono::milliseconds pause) {
    const auto request =
        protocol::rtu::frame(1, std::vector<std::uint8_t>{0x06, 0x00, 42, static_cast<std::uint8_t>(goal >> 8),
                                                          static_cast<std::uint8_t>(goal & 0xFF)});
    int answered = 0;
    for (int i = 0; i < writes; ++i) {
      if (i > 0) std::this_thread::sleep_for(pause);  // the PLC's cycle, not a wait for state
      if (plc_.ask(request, request.size()) == request) ++answered;
    }
    return answered;
  }

  PlcLine plc_;
  std::unique_ptr<test::EchoingAdapter> adapter_;  // the line's ends outlive the gateway's port
  std::unique_ptr<testing::SimulatedGateway> gateway_;
  std::atomic<int> goal_writes_{0};
};

TEST_F(CyclicWrites, APlcWritingTheSameGoalEveryCycleIsAnsweredEveryTime) {
  // An FC06 answer is its request byte for byte: the same frame again 100 ms later is the PLC's
  // next write, not an echo of the answer.
  start("{device: \"@PLC@\", baud: 115200}");
  constexpr int kWrites = 20;
  EXPECT_EQ(write_unchanged_goal(1800, kWrites, 100ms), kWrites);
  EXPECT_TRUE(plc_.unasked(50ms).empty());
  EXPECT_EQ(goal_writes_.load(), kWrites);  // each write reached the servo
  EXPECT_EQ(gateway_->bus().read_field(1, "goal_position"), 1800);
  const auto counted = stats();
  EXPECT_EQ(counted.requests, static_cast<std::uint64_t>(kWrites));
  EXPECT_EQ(counted.answers, static_cast<std::uint64_t>(kWrites));
  EXPECT_EQ(counted.echoes, 0u);
  EXPECT_EQ(counted.dropped_frames + counted.crc_errors + counted.silent_units, 0u);
}

// The port's role is checked by the gate every way in passes (gateway/service/access_gate.h): a
// write its role may not make is answered 0x01 without reaching the servo, logged with the port's
// name, and counted in the port's role_refusals; a read passes.
TEST_F(CyclicWrites, AWriteThePortsRoleMayNotMakeIsRefusedByTheGateLoggedAndCounted) {
  testing::LogCapture log;
  start("{device: \"@PLC@\", baud: 115200, role: read}");
  const auto write = protocol::rtu::frame(1, std::vector<std::uint8_t>{0x06, 0x00, 42, 0x07, 0x08});
  EXPECT_EQ(plc_.ask(write, 5), protocol::rtu::frame(1, std::vector<std::uint8_t>{0x86, 0x01}));
  EXPECT_EQ(goal_writes_.load(), 0);
  EXPECT_EQ(stats().role_refusals, 1u);
  EXPECT_TRUE(
      log.contains("rtu slave " + plc_.path() + ": unit 1 FC06 refused (0x01) for role read: role read may only read"))
      << log.text();
  const auto read = protocol::rtu::frame(1, std::vector<std::uint8_t>{0x03, 0x00, 42, 0x00, 0x01});
  EXPECT_EQ(plc_.ask(read, 7).size(), 7u);  // address, FC03, byte count, one register, CRC
  EXPECT_EQ(stats().role_refusals, 1u);
}

// The adapter hands every answer back to the port at once; the PLC's next write comes 100 ms after
// its answer. The echo is dropped and counted, the writes are all answered once.
struct EchoCase {
  const char* name;
  const char* port;
};
void PrintTo(const EchoCase& echo, std::ostream* out) { *out << "echo: " << echo.name; }

class EchoingAdapterCyclicWrites : public CyclicWrites, public ::testing::WithParamInterface<EchoCase> {};

TEST_P(EchoingAdapterCyclicWrites, TheEchoIsDroppedAndCountedAndEveryWriteAnsweredOnce) {
  start(GetParam().port, /*echoing=*/true);
  constexpr int kWrites = 10;
  EXPECT_EQ(write_unchanged_goal(2100, kWrites, 100ms), kWrites);
  EXPECT_TRUE(plc_.unasked(100ms).empty());  // no echo was answered as a request
  EXPECT_EQ(goal_writes_.load(), kWrites);
  EXPECT_EQ(gateway_->bus().read_field(1, "goal_position"), 2100);
  // The last echo may still be on its way when the PLC has its answer.
  EXPECT_TRUE(test::eventually([&] { return stats().echoes == static_cast<std::uint64_t>(kWrites); },
                               "every answer's echo counted"));
  const auto counted = stats();
  EXPECT_EQ(counted.requests, static_cast<std::uint64_t>(kWrites));
  EXPECT_EQ(counted.answers, static_cast<std::uint64_t>(kWrites));
  EXPECT_EQ(counted.dropped_frames + counted.crc_errors + counted.silent_units, 0u);
}

// auto: with a 30 ms t3.5, so that a loaded machine's relay and port thread (both woken by the
// echo) stay inside the window; on: the default t3.5 and its 50 ms for a late adapter.
INSTANTIATE_TEST_SUITE_P(Echo, EchoingAdapterCyclicWrites,
                         ::testing::Values(EchoCase{"auto", "{device: \"@PLC@\", baud: 115200, frame_gap: 30000us}"},
                                           EchoCase{"on", "{device: \"@PLC@\", baud: 115200, echo: on}"}),
                         [](const ::testing::TestParamInfo<EchoCase>& info) { return std::string(info.param.name); });

}  // namespace
}  // namespace sms::gateway
