// A silent servo never stalls its bus (docs/SAFETY.md "How long a stop can take", docs/DECISIONS.md
// "Late answers"): real sms-sim and sms-gateway processes, servos 1-3 of one protocol, servo 3
// offline from the start, `response_timeout_ms` 200 (and 1000 on feetech), `retries: 2`, a
// watchdog of the shortest timeout --check-config accepts (the bus's worst transaction + 1 ms).
// A PLC writes servo 1 every 200 ms: every write is carried out (none waits out servo 3, the
// watchdog never trips while the PLC is alive, the first write after start is not held up by the
// start-up stop). Then the PLC goes silent: the watchdog trips, servo 1 stops (the simulator's
// witness), servo 3 is owed its stop, and on packet buses the gateway's own figure for the stop
// (last feed -> its frames on the wire) stays inside the documented bound, timeout_ms + one worst
// transaction (on modbus-rtu the stop counts as failed, one write per servo: no figure, the failure
// counted). bench/silent_servo_stop measures the same over many trials.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <string>
#include <vector>

#include "safety_support.h"
#include "tests/support/eventually.h"

namespace sms::e2e {
namespace {

constexpr int kRetries = 2;
constexpr int kPlcWrites = 15;
constexpr auto kPlcPeriod = std::chrono::milliseconds{200};
constexpr int kBus0LastStopLatency = 116;  // 116-117: µs, 32-bit

// config::worst_transaction for an 8N1 bus: a fence and the request, every attempt each, each
// attempt the response timeout plus 256 bytes each way on the wire.
int worst_transaction_ms(int baud, int response_timeout_ms) {
  const long wire_ms = (2L * 256 * 10 * 1000 + baud - 1) / baud;
  return static_cast<int>((response_timeout_ms + wire_ms) * 2 * (1 + kRetries));
}

void silent_servo_never_stalls_the_bus(const Protocol& p, int response_timeout_ms) {
  TempDir dir;
  const std::string rest = p.sim_servo.substr(p.sim_servo.find(':'));
  SimProcess sim(dir, "line", {"--servo", "1" + rest, "--servo", "2" + rest, "--servo", "3" + rest});
  ASSERT_EQ(sim.control("offline 3"), "ok");
  const int worst = worst_transaction_ms(p.baud, response_timeout_ms);
  const int timeout = worst + 1;
  std::string yaml = "buses:\n  - {name: line, device: \"" + sim.pty() + "\", protocol: " + p.bus_protocol +
                     ", baud: " + std::to_string(p.baud) +
                     ", response_timeout_ms: " + std::to_string(response_timeout_ms) +
                     ", retries: " + std::to_string(kRetries) + ", watchdog: {timeout_ms: " + std::to_string(timeout) +
                     ", feed: any_write}}\nservos:\n";
  for (int id = 1; id <= 3; ++id) yaml += "  - {bus: line, id: " + std::to_string(id) + ", table: " + p.table + "}\n";
  GatewayProcess gateway = GatewayProcess::with_config(dir, yaml, 1);
  const auto log = [&] { return gateway.process().output(); };

  ModbusClient plc(gateway.port(), kUnit, std::chrono::seconds{15});
  ModbusClient hmi(gateway.port(), kGateway);
  // The longest the watchdog can have gone unfed while the PLC was alive, by the PLC's clock: a
  // write feeds it between being sent and being answered, so two feeds are at most (a write's
  // answer - the previous write's sending) apart. Beyond the timeout (a loaded machine) a trip is
  // the watchdog's rule, not a fault of the gateway, and the test cannot claim "never tripped".
  auto previous_sent = std::chrono::steady_clock::now();
  std::chrono::steady_clock::duration widest_gap{};
  const auto fed = [&](std::chrono::steady_clock::time_point sent) {
    widest_gap = std::max(widest_gap, std::chrono::steady_clock::now() - previous_sent);
    previous_sent = sent;
  };
  const auto starved = [&] { return widest_gap >= std::chrono::milliseconds{timeout}; };
  const auto starved_text = [&] {
    return "this machine left the " + std::to_string(timeout) + " ms watchdog unfed for up to " +
           std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(widest_gap).count()) +
           " ms while the PLC was alive: a trip is its rule, nothing to assert";
  };
  for (const Write& write : p.spin) {
    const auto sent = std::chrono::steady_clock::now();
    const auto answer = plc.write_register(write.address, write.value);
    fed(sent);
    ASSERT_TRUE(answer.ok()) << "the first writes after start: " << write.address << " := " << write.value << ": "
                             << answer.error << "\n"
                             << log();
  }
  const Write& cyclic = p.spin.back();  // a motion write: refused (0x04) once the watchdog has tripped
  for (int i = 0; i < kPlcWrites; ++i) {
    const auto sent = std::chrono::steady_clock::now();
    const auto answer = plc.write_register(cyclic.address, cyclic.value);
    fed(sent);
    if (!answer.ok() && starved()) GTEST_SKIP() << starved_text();
    ASSERT_TRUE(answer.ok()) << "write " << i << " of a live PLC: " << answer.error << " (exception "
                             << answer.exception << ")\n"
                             << log();
    std::this_thread::sleep_until(sent + kPlcPeriod);
  }
  const auto trips = hmi.read_input(kBus0Trips, 2);
  ASSERT_TRUE(trips.ok()) << trips.error;
  testing::Test::RecordProperty(
      "widest_feed_gap_ms",
      static_cast<int>(std::chrono::duration_cast<std::chrono::milliseconds>(widest_gap).count()));
  if (trips.values != std::vector<std::uint16_t>{0, 0} && starved()) GTEST_SKIP() << starved_text();
  EXPECT_EQ(trips.values, (std::vector<std::uint16_t>{0, 0})) << "the watchdog tripped while the PLC was alive";

  // The PLC goes silent: the watchdog stops servo 1 and owes servo 3 its stop.
  ASSERT_TRUE(
      eventually([&] { return hmi.read_input(kBus0WatchdogState, 1).values == std::vector<std::uint16_t>{kTripped}; },
                 "the watchdog's trip", std::chrono::milliseconds{timeout + 10'000}))
      << log();
  if (!p.torque_field.empty()) {
    EXPECT_TRUE(eventually([&] { return sim.field(1, "present_speed") == 0; }, "servo 1 stopped")) << log();
  }
  EXPECT_TRUE(eventually([&] { return hmi.read_input(kOwedStops, 1).values == std::vector<std::uint16_t>{1}; },
                         "servo 3 owed its stop"))
      << log();
  // The gateway's figure for the stop, or, where the stop counts as failed (modbus-rtu: one write
  // per servo, and servo 3's cannot be carried out), the failure counted.
  std::uint32_t latency_us = 0;
  std::uint32_t failed = 0;
  ASSERT_TRUE(eventually(
      [&] {
        const auto figure = hmi.read_input(kBus0LastStopLatency, 2);
        const auto failures = hmi.read_input(kFailedStops, 2);
        if (!figure.ok() || !failures.ok()) return false;
        latency_us = std::uint32_t{figure.values[0]} << 16 | figure.values[1];
        failed = std::uint32_t{failures.values[0]} << 16 | failures.values[1];
        return latency_us != 0 || failed != 0;
      },
      "the stop's latency registers, or its failure counted"))
      << log();
  if (p.bus_protocol != "modbus-rtu") {
    // A packet bus's stop is one SYNC WRITE: the offline servo is owed its stop, the stop did not fail.
    EXPECT_EQ(failed, 0U) << log();
    // The documented bound (docs/SAFETY.md): timeout_ms + one worst transaction + the stop's frames.
    const auto bound_us = static_cast<std::uint32_t>((timeout + worst) * 1000);
    EXPECT_NE(latency_us, 0U);
    EXPECT_LE(latency_us, bound_us) << "watchdog " << timeout << " ms, worst transaction " << worst << " ms\n" << log();
  } else {
    EXPECT_GE(failed, 1U) << log();
  }
  testing::Test::RecordProperty("stop_latency_us", static_cast<int>(latency_us));
}

class SilentServo : public testing::TestWithParam<Protocol> {};

TEST_P(SilentServo, NeverStallsItsBusAt200MsResponseTimeout) { silent_servo_never_stalls_the_bus(GetParam(), 200); }

INSTANTIATE_TEST_SUITE_P(EveryProtocol, SilentServo,
                         testing::Values(kSafetyProtocols[0], kSafetyProtocols[2], kSafetyProtocols[3]), protocol_name);

TEST(SilentServoSlowLine, NeverStallsItsBusAt1000MsResponseTimeout) {
  silent_servo_never_stalls_the_bus(kSafetyProtocols[0], 1000);
}

}  // namespace
}  // namespace sms::e2e
