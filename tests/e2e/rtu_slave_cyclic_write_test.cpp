// A PLC on the upstream Modbus RTU port (docs/RTU_PANELS.md) writing an unchanged goal every
// cycle, as PLCs do: an FC06 answer is its request byte for byte, so the same frame comes again
// each cycle and each must be answered (not taken for the adapter's echo of the last answer), or
// the PLC waits out its response timeout and the bus watchdog trips while the PLC is alive.
// sms-sim on a pty, sms-gateway on a socat pty pair, a libmodbus RTU master; the witnesses are the
// gateway unit's watchdog registers, the simulator's servo and /metrics.
#include <gtest/gtest.h>
#include <modbus/modbus.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

// Gateway unit 255 (docs/PLC_GUIDE.md "Safety"): bus 0's watchdog.
constexpr int kWatchdogState = 110;  // 0 off, 1 armed, 2 running, 3 tripped
constexpr int kWatchdogTrips = 112;  // 32 bits, high word first
constexpr std::uint16_t kRunning = 2;
constexpr auto kPlcCycle = std::chrono::milliseconds{100};

// Two pty ends joined by socat (two RS-485 adapters and a cable): the gateway opens one, the PLC
// the other.
class PtyPair {
 public:
  PtyPair(const TempDir& dir, const std::string& name)
      : gateway_end_(dir.file(name + "-up")), master_end_(dir.file(name + "-plc")) {
    socat_ = std::make_unique<ChildProcess>(std::vector<std::string>{
        "/usr/bin/socat", "pty,raw,echo=0,link=" + gateway_end_, "pty,raw,echo=0,link=" + master_end_});
    if (!eventually([&] { return std::filesystem::exists(gateway_end_) && std::filesystem::exists(master_end_); })) {
      throw std::runtime_error("socat made no pty pair:\n" + socat_->output());
    }
  }
  ~PtyPair() {
    socat_->signal(SIGTERM);
    socat_->wait_exit(10s);
  }
  const std::string& gateway_end() const { return gateway_end_; }
  const std::string& master_end() const { return master_end_; }

 private:
  std::string gateway_end_;
  std::string master_end_;
  std::unique_ptr<ChildProcess> socat_;
};

// A PLC as libmodbus is one: an RTU master with a 1 s response timeout.
class Plc {
 public:
  Plc(const std::string& device, int baud, char parity) {
    ctx_ = modbus_new_rtu(device.c_str(), baud, parity, 8, 1);
    if (ctx_ == nullptr) throw std::runtime_error("modbus_new_rtu failed");
    modbus_set_response_timeout(ctx_, 1, 0);
    if (modbus_connect(ctx_) != 0) {
      const std::string reason = modbus_strerror(errno);
      modbus_free(ctx_);
      throw std::runtime_error("open " + device + ": " + reason);
    }
    modbus_set_slave(ctx_, 1);
  }
  ~Plc() {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
  Plc(const Plc&) = delete;
  Plc& operator=(const Plc&) = delete;

  // FC06; empty when answered, else what libmodbus said (a timeout, an exception).
  std::string write_register(int address, std::uint16_t value) {
    return modbus_write_register(ctx_, address, value) == 1 ? std::string() : modbus_strerror(errno);
  }

 private:
  modbus_t* ctx_ = nullptr;
};

// What the PLC saw, and the watchdog after each of its cycles.
struct CyclicRun {
  int answered = 0;
  std::vector<std::string> failures;  // "write 3: Connection timed out"
  std::vector<std::uint16_t> states;  // unit 255's watchdog state after each write
  // The longest the watchdog can have gone unfed, by the PLC's clock: a write feeds it somewhere
  // between being sent and being answered, so two feeds are at most (one write's answer - the
  // previous write's sending) apart; a write refused (0x0B while a loaded machine held the
  // simulator past its response timeout and the servo went offline) feeds nothing, so the gap runs
  // on through it. A loaded machine can stretch it beyond the watchdog's timeout, and then a trip
  // is the product's rule, not a fault.
  std::chrono::steady_clock::duration widest_feed_gap{};
};

// Whether the PLC fed the watchdog at least once per `timeout` all along: a test asserts that the
// watchdog never tripped only where it did.
bool fed_in_time(const CyclicRun& run, std::chrono::milliseconds timeout) { return run.widest_feed_gap < timeout; }
std::string feed_gap_text(const CyclicRun& run) {
  return std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(run.widest_feed_gap).count()) + " ms";
}

// The PLC switches servo 1's torque on (holding 40), then writes `goal` to holding 42 (goal
// position) `writes` times, one FC06 per cycle; an HMI looks at the watchdog over Modbus TCP after
// each (reads never feed it).
CyclicRun write_unchanged_goal(const std::string& device, int baud, char parity, std::uint16_t tcp_port,
                               std::uint16_t goal, int writes) {
  Plc plc(device, baud, parity);
  ModbusClient hmi(tcp_port, 255);
  CyclicRun run;
  auto previous_sent = std::chrono::steady_clock::now();
  if (const std::string failure = plc.write_register(40, 1); !failure.empty()) {
    run.failures.push_back("torque on: " + failure);
    return run;
  }
  auto next = std::chrono::steady_clock::now();
  for (int i = 0; i < writes; ++i) {
    std::this_thread::sleep_until(next);  // the PLC's cycle, not a wait for state
    next += kPlcCycle;
    const auto sent = std::chrono::steady_clock::now();
    const std::string failure = plc.write_register(42, goal);
    run.widest_feed_gap = std::max(run.widest_feed_gap, std::chrono::steady_clock::now() - previous_sent);
    if (failure.empty()) {
      previous_sent = sent;  // a refused write (0x0B while the servo was offline) fed nothing
      ++run.answered;
    } else {
      run.failures.push_back("write " + std::to_string(i) + ": " + failure);
    }
    const auto state = hmi.read_input(kWatchdogState, 1);
    run.states.push_back(state.ok() ? state.values[0] : 0xFFFF);
  }
  return run;
}

// The writes the gateway answered with exception 0x0B (its servo did not answer): an answer all
// the same, the frame not taken for an echo. The gateway's rule where the servo missed its
// response timeouts and went offline until its probe, as a loaded machine can make the simulator
// do: counted apart, and allowed only where the gateway logged a servo offline.
int answered_servo_silent(const CyclicRun& run) {
  return static_cast<int>(std::count_if(run.failures.begin(), run.failures.end(), [](const std::string& failure) {
    return failure.ends_with(": Target device failed to respond");
  }));
}

std::string listed(const std::vector<std::string>& lines) {
  std::string text;
  for (const auto& line : lines) text += line + "\n";
  return text;
}

void expect_every_write_answered(const CyclicRun& run, int writes, const std::string& gateway_output) {
  const int servo_silent = answered_servo_silent(run);
  if (servo_silent > 0) {
    EXPECT_NE(gateway_output.find(" offline ("), std::string::npos)
        << servo_silent << " writes answered 0x0B while no servo went offline:\n"
        << listed(run.failures) << gateway_output;
  }
  EXPECT_EQ(run.answered + servo_silent, writes) << listed(run.failures) << gateway_output;
}

std::uint32_t watchdog_trips(std::uint16_t tcp_port) {
  ModbusClient hmi(tcp_port, 255);
  const auto trips = hmi.read_input(kWatchdogTrips, 2);
  if (!trips.ok()) throw std::runtime_error("gateway unit trips register: " + trips.error);
  return (static_cast<std::uint32_t>(trips.values[0]) << 16) | trips.values[1];
}

// A 500 ms watchdog fed by any write, torque off on a trip (the simulator would show it).
constexpr const char* kConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: arm, device: "@ARM@", protocol: feetech, baud: 1000000,
     watchdog: {timeout_ms: 500, feed: any_write, action: torque_off}}
servos:
  - {bus: arm, id: 1, table: sts}
logging: {metrics_listen: "127.0.0.1:0"}
modbus_rtu_slave:
  - {device: "@PLC@", baud: 19200}
)";

TEST(RtuSlaveCyclicWrite, APlcWritingAnUnchangedGoalEvery100MsIsAlwaysAnsweredAndKeepsA500MsWatchdogFed) {
  TempDir dir;
  SimProcess arm(dir, "arm", {"--servo", "1:sts"});
  PtyPair line(dir, "plc");
  std::string yaml = substitute(kConfig, "@ARM@", arm.pty());
  yaml = substitute(yaml, "@PLC@", line.gateway_end());
  auto gateway = GatewayProcess::with_config(dir, yaml, 1);
  const std::string marker = "/healthz on http://127.0.0.1:";
  const auto metrics_line = gateway.process().wait_for_line(marker, 15s);
  ASSERT_TRUE(metrics_line) << gateway.process().output();
  const auto metrics_port =
      static_cast<std::uint16_t>(std::stoi(metrics_line->substr(metrics_line->find(marker) + marker.size())));
  ASSERT_TRUE(gateway.process().wait_for_line("rtu slave " + line.gateway_end() + ": open at", 10s))
      << gateway.process().output();
  wait_until_polled(gateway.port(), 1);

  // 3 s of cycles: six times the watchdog's timeout, so one unanswered write (a PLC waiting out
  // its 1 s response timeout) would trip it.
  constexpr int kWrites = 30;
  const CyclicRun run = write_unchanged_goal(line.master_end(), 19200, 'E', gateway.port(), 2600, kWrites);
  RecordProperty("widest_feed_gap", feed_gap_text(run));
  if (!fed_in_time(run, 500ms) && watchdog_trips(gateway.port()) != 0) {
    GTEST_SKIP() << "this machine left the 500 ms watchdog unfed for up to " << feed_gap_text(run)
                 << ": its trip is the watchdog's rule, nothing to assert";
  }
  expect_every_write_answered(run, kWrites, gateway.process().output());
  EXPECT_EQ(run.states, std::vector<std::uint16_t>(kWrites, kRunning)) << "the watchdog left running";
  EXPECT_EQ(watchdog_trips(gateway.port()), 0u);
  EXPECT_EQ(gateway.process().output().find("WATCHDOG TRIPPED"), std::string::npos) << gateway.process().output();
  // The simulator's servo: the goal written and held, the torque the PLC switched on never taken
  // off by a stop.
  EXPECT_EQ(arm.field(1, "goal_position"), 2600);
  EXPECT_EQ(arm.field(1, "torque_enable"), 1);
  EXPECT_TRUE(eventually([&] { return arm.field(1, "present_position") == 2600; }, "servo 1 at 2600"));
  // Every write (the torque one and the goals) counted as a request and answered; nothing dropped
  // as an echo or otherwise.
  const auto metrics = parse_exposition(http_request(metrics_port, "GET", "/metrics").body);
  const auto value = [&](const std::string& name) {
    return metrics.value("sms_gateway_rtu_slave_" + name + "{device=\"" + line.gateway_end() + "\"}");
  };
  EXPECT_EQ(value("requests_total"), std::to_string(kWrites + 1));
  EXPECT_EQ(value("answers_total"), std::to_string(kWrites + 1));
  EXPECT_EQ(value("echoes_total"), "0");
  EXPECT_EQ(value("dropped_frames_total"), "0");
  EXPECT_EQ(value("crc_errors_total"), "0");
}

TEST(RtuSlaveCyclicWrite, OnSimulateWithTheFlagTwentyIdenticalWritesGetTwentyAnswers) {
  // The flag's port (19200 8E1 unless given) and --simulate's 3000 ms watchdog.
  TempDir dir;
  PtyPair line(dir, "plc");
  GatewayProcess gateway({"--simulate", "--rtu-slave", line.gateway_end() + ":115200:none"}, 1);
  ASSERT_TRUE(gateway.process().wait_for_line("rtu slave " + line.gateway_end() + ": open at", 10s))
      << gateway.process().output();
  wait_until_polled(gateway.port(), 1);
  constexpr int kWrites = 20;
  const CyclicRun run = write_unchanged_goal(line.master_end(), 115200, 'N', gateway.port(), 1500, kWrites);
  RecordProperty("widest_feed_gap", feed_gap_text(run));
  if (!fed_in_time(run, 3000ms) && watchdog_trips(gateway.port()) != 0) {
    GTEST_SKIP() << "this machine left the 3000 ms watchdog unfed for up to " << feed_gap_text(run)
                 << ": its trip is the watchdog's rule, nothing to assert";
  }
  expect_every_write_answered(run, kWrites, gateway.process().output());
  EXPECT_EQ(run.states, std::vector<std::uint16_t>(kWrites, kRunning));
  EXPECT_EQ(watchdog_trips(gateway.port()), 0u);
  // The in-process simulator's servo, through the poll cache: it went to the goal.
  ModbusClient servo(gateway.port(), 1);
  EXPECT_TRUE(eventually(
      [&] {
        const auto position = servo.read_input(56, 1);
        return position.ok() && position.values[0] == 1500;
      },
      "servo 1 at 1500"));
}

}  // namespace
}  // namespace sms::e2e
