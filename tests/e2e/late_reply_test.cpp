// A late servo end to end (docs/DECISIONS.md "Late answers"): real sms-sim and sms-gateway
// processes, a libmodbus TCP client alternating FC03 reads of a constant block and of another
// block of the same size on one servo, while the simulator's `late` fault (its control socket)
// makes the servo answer after the gateway gave up — 50, 90, 150 and 400 ms late (one attempt
// is about 50 ms here, a whole transaction 150 ms), then toggled on and off. A servo's answer
// names no request, so a late one looks exactly like the answer to the next request of the same
// size: no read may ever be answered Ok with the other block's values. The two other servos of
// the bus stay online and answered all along (the late one costs the bus its attempts, no more),
// and what was dropped is counted (stray frames, fences).
#include <gtest/gtest.h>

#include <csignal>
#include <fstream>
#include <iostream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "tests/e2e/sim_motion.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using test::HttpConnection;
using test::parse_exposition;
using Registers = std::vector<std::uint16_t>;

// Per attempt 50 ms, three attempts.
constexpr int kTimeoutMs = 50;

constexpr const char* kFeetechConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: arm, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 20,
     offline_probe_period_ms: 100, response_timeout_ms: @TIMEOUT@, retries: 2}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sts}
  - {unit: 3, bus: arm, id: 3, table: sts}
)";

constexpr const char* kRtuConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: lift, device: "@DEVICE@", protocol: modbus-rtu, baud: 115200, poll_period_ms: 20,
     offline_probe_period_ms: 100, response_timeout_ms: @TIMEOUT@, retries: 2}
servos:
  - {unit: 1, bus: lift, id: 1, table: smsmb}
  - {unit: 2, bus: lift, id: 2, table: smsmb}
  - {unit: 3, bus: lift, id: 3, table: smsmb}
)";

std::uint16_t port_after(ChildProcess& process, const std::string& marker) {
  const auto line = process.wait_for_line(marker, 15s);
  if (!line) throw std::runtime_error("no line with '" + marker + "':\n" + process.output());
  return static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
}

std::string metrics_text(std::uint16_t port) {
  HttpConnection connection(port);
  connection.send("GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n");
  const auto response = connection.read_response();
  if (!response) throw std::runtime_error("no answer from /metrics");
  return response->body;
}

struct Tally {
  int ok_constant = 0;
  int ok_other = 0;
  int refused = 0;
  int others_checked = 0;
  int others_late = 0;      // checks that found another servo offline for its own late answers
  int others_held = 0;      // checks that found another servo offline unanswered while the machine held the simulator
  int others_collided = 0;  // ... after answers collided on the line since the check before
  long long collisions_seen = 0;  // the simulator's count at the last check
};

// Replies that overlapped another on the simulated wire, so far (sms-sim `stats`).
long long collisions(SimProcess& sim) {
  const std::string stats = sim.control("stats");
  const auto at = stats.find("collisions=");
  if (at == std::string::npos) throw std::runtime_error("sms-sim stats: " + stats);
  return std::stoll(stats.substr(at + 11));
}

// The other servos of the bus (units 2 and 3): online (input register 1001). Offline only for
// answering late themselves (register 1008 = 2: their own address on their late answers, which a
// loaded machine can make of any servo: the product's rule), or for no answer (1) where the
// simulator witnessed the machine holding it an attempt's time in the last seconds; never for the
// late servo's answers.
void others_answer(SimProcess& sim, std::vector<std::unique_ptr<ModbusClient>>& others, const std::string& phase,
                   Tally& tally) {
  constexpr std::uint16_t kOnline = 1001, kOfflineReason = 1008, kAnswersLate = 2, kNoAnswer = 1;
  for (std::size_t i = 0; i < others.size(); ++i) {
    const int unit = static_cast<int>(i) + 2;
    const auto online = others[i]->read_input(kOnline, kOfflineReason - kOnline + 1);
    ASSERT_TRUE(online.ok()) << phase << ": unit " << unit << ": " << online.error;
    if (online.values.front() == 0 && online.values.back() == kAnswersLate) {
      ++tally.others_late;
      continue;
    }
    if (online.values.front() == 0 && online.values.back() == kNoAnswer &&
        sim_held(sim, std::chrono::milliseconds(kTimeoutMs), std::chrono::steady_clock::now() - 3s)) {
      ++tally.others_held;
      continue;
    }
    // On one RS-485 line a late answer that overlaps another servo's answer destroys both: where
    // the simulator saw such collisions since the last check, that servo's attempts can all have
    // been lost that way (retried, then offline: the product's rule on a shared line).
    if (online.values.front() == 0 && online.values.back() == kNoAnswer && collisions(sim) > tally.collisions_seen) {
      ++tally.others_collided;
      continue;
    }
    EXPECT_EQ(online.values.front(), 1) << phase << ": unit " << unit << " went offline beside the late servo, reason "
                                        << online.values.back();
  }
  ++tally.others_checked;
  tally.collisions_seen = collisions(sim);
}

// Reads `constant` and `other` in turn on `unit` for `duration`; every Ok answer of the constant
// block must be `expected`, and no Ok answer of the other block may be it.
void read_in_turn(SimProcess& sim, ModbusClient& unit, std::vector<std::unique_ptr<ModbusClient>>& others, int constant,
                  int other, int count, const Registers& expected, std::chrono::milliseconds duration,
                  const std::string& phase, Tally& tally) {
  const auto until = std::chrono::steady_clock::now() + duration;
  for (int i = 0; std::chrono::steady_clock::now() < until; ++i) {
    if (i % 4 == 0) others_answer(sim, others, phase, tally);
    const bool constant_turn = i % 2 == 0;
    const auto answer = unit.read_holding(constant_turn ? constant : other, count);
    if (!answer.ok()) {
      ++tally.refused;
      continue;
    }
    if (constant_turn) {
      ++tally.ok_constant;
      EXPECT_EQ(answer.values, expected) << phase << ": the constant block answered with other values";
    } else {
      ++tally.ok_other;
      EXPECT_NE(answer.values, expected) << phase << ": the other block answered with the constant block's values";
    }
  }
}

void late_servo_never_yields_a_wrong_value(SimProcess& sim, GatewayProcess& gateway, int unit_id, int constant,
                                           int other, int count, const std::string& labels) {
  for (int polled = 1; polled <= 3; ++polled) wait_until_polled(gateway.port(), polled);
  ModbusClient unit(gateway.port(), unit_id, std::chrono::seconds{10});
  std::vector<std::unique_ptr<ModbusClient>> others;
  for (int other_unit = 2; other_unit <= 3; ++other_unit) {
    others.push_back(std::make_unique<ModbusClient>(gateway.port(), other_unit));
  }
  const auto reference = unit.read_holding(constant, count);
  ASSERT_TRUE(reference.ok()) << reference.error;
  const Registers expected = reference.values;
  const auto first_other = unit.read_holding(other, count);
  ASSERT_TRUE(first_other.ok()) << first_other.error;
  ASSERT_NE(first_other.values, expected) << "the two blocks must differ for a mix-up to show";

  Tally tally;
  for (const int lateness : {50, 90, 150, 400}) {
    ASSERT_EQ(sim.control("late 1 " + std::to_string(lateness)), "ok");
    read_in_turn(sim, unit, others, constant, other, count, expected, 1200ms, "late " + std::to_string(lateness),
                 tally);
    ASSERT_EQ(sim.control("late 1 0"), "ok");
    read_in_turn(sim, unit, others, constant, other, count, expected, 600ms, "after late " + std::to_string(lateness),
                 tally);
  }
  // Toggled while the reads go on, as a flaky adapter or a busy servo would.
  for (int round = 0; round < 8; ++round) {
    ASSERT_EQ(sim.control(round % 2 == 0 ? "late 1 " + std::to_string(kTimeoutMs * 2) : "late 1 0"), "ok");
    read_in_turn(sim, unit, others, constant, other, count, expected, 200ms, "toggling, round " + std::to_string(round),
                 tally);
  }
  ASSERT_EQ(sim.control("late 1 0"), "ok");
  // On time again: answered again, with the right values.
  EXPECT_TRUE(eventually([&] { return unit.read_holding(constant, count).ok(); }));
  read_in_turn(sim, unit, others, constant, other, count, expected, 500ms, "on time", tally);
  EXPECT_GT(tally.ok_constant, 0);
  EXPECT_GT(tally.ok_other, 0);
  EXPECT_GT(tally.others_checked, 0);
  std::cout << "answered ok: constant " << tally.ok_constant << ", other " << tally.ok_other << "; refused "
            << tally.refused << "; the other servos checked " << tally.others_checked << " times, " << tally.others_late
            << " of them one offline for its own late answers, " << tally.others_held
            << " one offline unanswered while the machine held the simulator, " << tally.others_collided
            << " one offline unanswered after answers collided on the line\n";

  const auto metrics = parse_exposition(metrics_text(port_after(gateway.process(), "/healthz on http://127.0.0.1:")));
  const auto counted = [&](const std::string& family) {
    const std::string value = metrics.value(family + labels);
    EXPECT_FALSE(value.empty()) << family << labels << " missing";
    return value.empty() ? 0.0 : std::stod(value);
  };
  EXPECT_GT(counted("sms_gateway_bus_stray_frames_total") + counted("sms_gateway_bus_stray_bytes_total"), 0.0)
      << "the late answers dropped were not counted";
  EXPECT_GT(counted("sms_gateway_bus_fences_total"), 0.0) << "no fence went before a read an owed answer looked like";
}

TEST(LateReply, FeetechLateServoNeverAnswersOneReadWithAnotherReadsValues) {
  TempDir dir;
  SimProcess sim(dir, "arm", {"--servo", "1:sts", "--servo", "2:sts", "--servo", "3:sts"});
  const std::string path = dir.file("gateway.yaml");
  std::ofstream(path) << substitute(substitute(kFeetechConfig, "@DEVICE@", sim.pty()), "@TIMEOUT@",
                                    std::to_string(kTimeoutMs));
  GatewayProcess gateway({"--config", path, "--metrics", "127.0.0.1:0"}, 1);
  // Holding 9-12: the angle limits (constant 0, 0, 4095, 0); 60-63: load, voltage, temperature.
  late_servo_never_yields_a_wrong_value(sim, gateway, 1, 9, 60, 4, R"({bus="arm",protocol="feetech"})");
}

TEST(LateReply, ModbusRtuLateServoNeverAnswersOneReadWithAnotherReadsValues) {
  TempDir dir;
  SimProcess sim(dir, "lift",
                 {"--servo", "1:smsmb:modbus-rtu:115200", "--servo", "2:smsmb:modbus-rtu:115200", "--servo",
                  "3:smsmb:modbus-rtu:115200"});
  const std::string path = dir.file("gateway.yaml");
  std::ofstream(path) << substitute(substitute(kRtuConfig, "@DEVICE@", sim.pty()), "@TIMEOUT@",
                                    std::to_string(kTimeoutMs));
  GatewayProcess gateway({"--config", path, "--metrics", "127.0.0.1:0"}, 1);
  // Holding 0x0D-0x0E: the angle limits; 0x11-0x12: the position gains (both constant, different).
  late_servo_never_yields_a_wrong_value(sim, gateway, 1, 0x0D, 0x11, 2, R"({bus="lift",protocol="modbus-rtu"})");
}

// The witness the allowance above asks: a simulator the machine held (here: stopped by a signal)
// says so, with how long; one never held says "none" of that length.
TEST(SimHolds, ASimulatorTheMachineHeldReportsTheHold) {
  TempDir dir;
  SimProcess sim(dir, "line", {"--servo", "1:sts"});
  const auto before = std::chrono::steady_clock::now();
  EXPECT_FALSE(sim_held(sim, 10s, before)) << sim.control("holds");
  sim.process().signal(SIGSTOP);
  std::this_thread::sleep_for(300ms);
  sim.process().signal(SIGCONT);
  EXPECT_TRUE(eventually([&] { return sim_held(sim, 250ms, before); }, "a hold of 250 ms or more"))
      << sim.control("holds");
  EXPECT_FALSE(sim_held(sim, 250ms, std::chrono::steady_clock::now())) << "none ended after now";
}

}  // namespace
}  // namespace sms::e2e
