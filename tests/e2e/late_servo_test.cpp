// A servo that answers late costs the others nothing (docs/DECISIONS.md "A servo that answers late",
// docs/PLC_GUIDE.md "A silent servo does not stall the bus"): real sms-sim and sms-gateway
// processes, servos 1-3 of one protocol, `retries: 2`, a watchdog of the shortest timeout
// --check-config accepts (the worst transaction + 1 ms). Servo 2 answers every request late
// (sms-sim `late 2 MS`) while an HMI reads it live over and over and a PLC writes servo 1 every
// 20 ms. Servo 2 goes offline with its own reason (input register 1008 = 2, gateway unit input
// register 16), its reads are refused at once (0x0B) instead of costing the bus its retries, the
// PLC's writes are all carried out and the watchdog never trips while the PLC feeds it in time;
// once servo 2 answers in time again its probe brings it back. On d55d no motor's own 500 ms
// heartbeat fires meanwhile (the simulator's witness, `motion ID` heartbeat_stops): servo 3
// turns throughout, and servo 2, probed while offline, too. Where a heartbeat stop does happen
// (a poll period longer than the heartbeat), the gateway says so and counts it.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "safety_support.h"
#include "sim_motion.h"
#include "tests/support/eventually.h"

namespace sms::e2e {
namespace {

constexpr int kRetries = 2;
constexpr int kPlcWrites = 150;
constexpr auto kPlcPeriod = std::chrono::milliseconds{20};
constexpr int kLate = 2;   // the servo that answers late
constexpr int kOther = 3;  // a servo that answers in time
// Servo unit input registers (docs/PLC_GUIDE.md "A servo unit").
constexpr int kFactOnline = 1001;
constexpr int kFactOfflineReason = 1008;
constexpr std::uint16_t kAnswersLate = 2;
constexpr int kLateServos = 16;  // gateway unit: servos offline because they answer late
constexpr int kGatewayBusy = 0x0B;

struct Case {
  Protocol protocol;
  int late_ms;
  int response_timeout_ms;
};

std::string case_name(const testing::TestParamInfo<Case>& info) {
  return info.param.protocol.name + "_" + std::to_string(info.param.late_ms) + "ms_late_at_" +
         std::to_string(info.param.response_timeout_ms) + "ms";
}

const Protocol& protocol_named(const std::string& name) {
  for (const Protocol& protocol : kSafetyProtocols) {
    if (protocol.name == name) return protocol;
  }
  throw std::invalid_argument("no protocol " + name);
}

// config::worst_transaction for an 8N1 bus: a fence and the request, every attempt each, each
// attempt the response timeout plus 256 bytes each way on the wire.
int worst_transaction_ms(int baud, int response_timeout_ms) {
  const long wire_ms = (2L * 256 * 10 * 1000 + baud - 1) / baud;
  return static_cast<int>((response_timeout_ms + wire_ms) * 2 * (1 + kRetries));
}

std::string bus_yaml(const Protocol& p, const std::string& pty, const std::string& extra) {
  std::string yaml = "buses:\n  - {name: line, device: \"" + pty + "\", protocol: " + p.bus_protocol +
                     ", baud: " + std::to_string(p.baud) + extra + "}\nservos:\n";
  for (int id = 1; id <= 3; ++id) yaml += "  - {bus: line, id: " + std::to_string(id) + ", table: " + p.table + "}\n";
  return yaml;
}

class LateServo : public testing::TestWithParam<Case> {};

TEST_P(LateServo, GoesOfflineWithItsOwnReasonAndCostsTheOthersNothing) {
  const Case& c = GetParam();
  const Protocol& p = c.protocol;
  const bool d55d = p.bus_protocol == "d55d";
  TempDir dir;
  const std::string rest = p.sim_servo.substr(p.sim_servo.find(':'));
  SimProcess sim(dir, "line", {"--servo", "1" + rest, "--servo", "2" + rest, "--servo", "3" + rest});
  const int timeout = worst_transaction_ms(p.baud, c.response_timeout_ms) + 1;
  GatewayProcess gateway = GatewayProcess::with_config(
      dir,
      bus_yaml(p, sim.pty(),
               ", response_timeout_ms: " + std::to_string(c.response_timeout_ms) +
                   ", retries: " + std::to_string(kRetries) + ", watchdog: {timeout_ms: " + std::to_string(timeout) +
                   ", feed: any_write}"),
      1);
  const auto log = [&] { return gateway.process().output(); };
  ModbusClient plc(gateway.port(), kUnit, std::chrono::seconds{15});
  ModbusClient gateway_unit(gateway.port(), kGateway);
  ModbusClient late_unit(gateway.port(), kLate);
  if (d55d) {
    // Servos 2 and 3 turn (speed mode) for the whole test: a heartbeat stop would end that.
    for (const int id : {kLate, kOther}) {
      ModbusClient unit(gateway.port(), id);
      for (const Write& write : p.spin) {
        ASSERT_TRUE(unit.write_register(write.address, write.value).ok()) << "servo " << id << "\n" << log();
      }
    }
  }
  ASSERT_EQ(sim.control("late " + std::to_string(kLate) + " " + std::to_string(c.late_ms)), "ok");

  // The HMI: live reads of the late servo, as fast as they are answered.
  std::atomic<bool> hmi_done{false};
  std::atomic<int> hmi_busy{0};
  std::thread hmi([&] {
    ModbusClient reader(gateway.port(), kLate, std::chrono::seconds{15});
    while (!hmi_done.load()) {
      if (reader.read_holding(p.goal_address, 1).exception == kGatewayBusy) hmi_busy.fetch_add(1);
    }
  });
  // The PLC writes servo 1 every 20 ms; it measures by its own clock the longest the watchdog can
  // have gone unfed (a carried-out write's answer minus the previous carried-out write's sending;
  // a refused write feeds nothing): beyond the timeout a trip is the watchdog's rule on a loaded
  // machine, nothing to assert.
  auto previous_sent = std::chrono::steady_clock::now();
  std::chrono::steady_clock::duration widest_gap{};
  std::vector<std::string> failed_writes;
  int refused_offline = 0;  // 0x0B: servo 1 itself offline
  for (int i = 0; i < kPlcWrites; ++i) {
    const auto sent = std::chrono::steady_clock::now();
    const auto answer = plc.write_register(p.harmless.address, static_cast<std::uint16_t>(p.harmless.value + i % 2));
    widest_gap = std::max(widest_gap, std::chrono::steady_clock::now() - previous_sent);
    if (answer.ok()) {
      previous_sent = sent;
    } else if (answer.exception == 0x0B) {
      ++refused_offline;
    } else {
      failed_writes.push_back(std::to_string(i) + ": " + answer.error + " (exception " +
                              std::to_string(answer.exception) + ")");
    }
    std::this_thread::sleep_until(sent + kPlcPeriod);
  }
  const bool starved = widest_gap >= std::chrono::milliseconds{timeout};
  hmi_done = true;
  hmi.join();

  // Servo 2 is offline for answering late, and said so; the HMI's reads of it were refused at once.
  ASSERT_TRUE(eventually(
      [&] {
        const auto facts = late_unit.read_input(kFactOnline, kFactOfflineReason - kFactOnline + 1);
        return facts.ok() && facts.values.front() == 0 && facts.values.back() == kAnswersLate;
      },
      "servo 2 offline, reason 2 (answers late)"))
      << log();
  EXPECT_EQ(gateway_unit.read_input(kLateServos, 1).or_throw("late servos").at(0), 1);
  EXPECT_NE(log().find("servo 2 answers late"), std::string::npos) << log();
  EXPECT_GT(hmi_busy.load(), 0) << "no read of the late servo was refused with 0x0B";

  // The PLC's writes to servo 1 were all carried out, and the watchdog never tripped; except that
  // where this machine held the simulator past servo 1's own response timeout, servo 1 went
  // offline too (the log says so) and the writes meanwhile were answered 0x0B, the product's rule.
  EXPECT_TRUE(failed_writes.empty()) << failed_writes.size() << " writes to servo 1 failed, first "
                                     << failed_writes.front() << "\n"
                                     << log();
  if (refused_offline > 0) {
    EXPECT_NE(log().find("servo 1 offline"), std::string::npos)
        << refused_offline << " writes to servo 1 answered 0x0B while it was not offline\n"
        << log();
  }
  const auto trips = gateway_unit.read_input(kBus0Trips, 2).or_throw("trips");
  if (starved) {
    std::cout << "this machine left the " << timeout << " ms watchdog unfed for up to "
              << std::chrono::duration_cast<std::chrono::milliseconds>(widest_gap).count()
              << " ms while the PLC was alive: a trip is its rule, not asserted\n";
  } else {
    EXPECT_EQ(trips.at(0) << 16 | trips.at(1), 0) << log();
  }
  // The servo answering in time is polled all along.
  ModbusClient other(gateway.port(), kOther);
  EXPECT_EQ(other.read_input(kFactOnline, 1).or_throw("servo 3 online").at(0), 1) << log();

  if (d55d) {
    // No motor's own heartbeat fired: the offline one was probed inside it, the others polled.
    for (const int id : {kLate, kOther}) {
      EXPECT_EQ(motion_of(sim, id).heartbeat_stops, 0) << "servo " << id << "\n" << log();
    }
    EXPECT_EQ(log().find("without an instruction"), std::string::npos) << log();
  }

  // In time again: its probe brings it back, reason 0.
  ASSERT_EQ(sim.control("late " + std::to_string(kLate) + " 0"), "ok");
  ASSERT_TRUE(eventually(
      [&] {
        const auto facts = late_unit.read_input(kFactOnline, kFactOfflineReason - kFactOnline + 1);
        return facts.ok() && facts.values.front() == 1 && facts.values.back() == 0;
      },
      "servo 2 online again, reason 0"))
      << log();
  EXPECT_EQ(gateway_unit.read_input(kLateServos, 1).or_throw("late servos").at(0), 0);
}

INSTANTIATE_TEST_SUITE_P(EveryBusProtocol, LateServo,
                         testing::Values(Case{protocol_named("feetech_sts"), 50, 20},
                                         Case{protocol_named("feetech_sts"), 400, 20},
                                         Case{protocol_named("feetech_sts"), 150, 100},
                                         Case{protocol_named("d55d"), 50, 20}, Case{protocol_named("d55d"), 400, 20},
                                         Case{protocol_named("modbus_rtu_smsmb"), 50, 20}),
                         case_name);

// A d55d motor that goes longer than its heartbeat without an instruction (here a poll period
// of 700 ms, which --check-config warns about) stops by itself: the gateway logs it, counts it,
// and the simulator's witness agrees.
TEST(D55dHeartbeat, AGapLongerThanTheHeartbeatIsLoggedAndCounted) {
  const Protocol& p = protocol_named("d55d");
  TempDir dir;
  SimProcess sim(dir, "line", {"--servo", "1:d55d:d55d:115200"});
  const std::string yaml = config_for(p, sim.pty(), ", poll_period_ms: 700");
  {
    std::ofstream(dir.file("check.yaml")) << yaml;
    ChildProcess check({bin("sms-gateway"), "--check-config", dir.file("check.yaml")});
    ASSERT_EQ(check.wait_exit(std::chrono::seconds{10}), 0) << check.output();
    EXPECT_NE(check.output().find("its 500 ms heartbeat can stop it"), std::string::npos) << check.output();
  }
  GatewayProcess gateway = GatewayProcess::with_config(dir, yaml, 1);
  const auto log = [&] { return gateway.process().output(); };
  ModbusClient unit(gateway.port(), kUnit);
  for (const Write& write : p.spin) ASSERT_TRUE(unit.write_register(write.address, write.value).ok()) << log();
  ASSERT_TRUE(eventually([&] { return motion_of(sim, kUnit).heartbeat_stops > 0; },
                         "the motor's heartbeat stops it between two polls", std::chrono::seconds{10}))
      << log();
  ASSERT_TRUE(eventually(
      [&] {
        return log().find("went ") != std::string::npos && log().find("without an instruction") != std::string::npos;
      },
      "the gateway logs the gap"))
      << log();
}

}  // namespace
}  // namespace sms::e2e
