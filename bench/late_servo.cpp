// late_servo: what a servo that answers late costs the others (docs/DECISIONS.md "A servo that
// answers late", docs/PLC_GUIDE.md "A silent servo does not stall the bus").
//
//   late_servo [--seconds 5] [--quick 0|1]
//
// Three servos on a bus simulated in this process (wire timing on), the real sms-gateway as a
// child process with `response_timeout_ms` R, `retries: 2` and a watchdog of the shortest
// timeout --check-config accepts (the worst transaction + 1 ms). Servo 2 answers every request
// L ms late while an HMI reads it live back to back and a PLC writes servo 1 every 20 ms; on
// d55d, servos 2 and 3 turn the whole time. Per protocol (sts at 1 Mbit/s, d55d at 115 200),
// R (20, 100 ms) and L (20, 50, 90, 150, 400 ms): watchdog trips, the PLC's write latency
// against the worst transaction, the age of servo 3's cached data, whether servo 2 ended
// offline for answering late, and on d55d the motors' own heartbeat stops (the simulator's
// witness). --quick: sts, R 20, L 50 and 400 only. Talks to 127.0.0.1 only; bounded.
#include <algorithm>
#include <atomic>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;
using sms::modbus_map::TableId;
using sms::protocol::BusProtocol;

constexpr int kRetries = 2;
constexpr int kLate = 2;
constexpr int kOther = 3;
constexpr auto kPlcPeriod = 20ms;
constexpr int kBus0Trips = 112;           // gateway unit, 32 bits
constexpr int kFactCacheAge = 1002;       // servo unit input registers
constexpr int kFactOfflineReason = 1008;  // 2: answers late
constexpr std::uint16_t kAnswersLate = 2;

struct Write {
  int address;
  std::uint16_t value;
};

struct Bus {
  std::string name;
  TableId table;
  BusProtocol protocol;
  std::string bus_protocol;  // config
  std::uint32_t baud;
  Write harmless;           // the PLC's cyclic write to servo 1 (feeds the watchdog, moves nothing)
  int read_address;         // the HMI's live read of servo 2
  std::vector<Write> spin;  // d55d: speed mode, turning (a heartbeat stop would end it)
};

const std::vector<Bus> kBuses{
    {"sts", TableId::Sts, BusProtocol::Feetech, "feetech", 1000000, {41, 20}, 42, {}},
    {"d55d", TableId::D55d, BusProtocol::D55d, "d55d", 115200, {34, 20}, 30, {{6, 0}, {8, 0}, {32, 300}}},
};

// config::worst_transaction for an 8N1 bus.
int worst_transaction_ms(std::uint32_t baud, int response_timeout_ms) {
  const long wire_ms = (2L * 256 * 10 * 1000 + baud - 1) / baud;
  return static_cast<int>((response_timeout_ms + wire_ms) * 2 * (1 + kRetries));
}

void run_case(const Bus& bus_spec, int response_timeout_ms, int late_ms, std::chrono::milliseconds duration) {
  sms::simulator::BusOptions options;
  for (std::uint8_t id = 1; id <= 3; ++id) {
    options.servos.push_back(sms::simulator::ServoConfig{id, bus_spec.table, bus_spec.protocol, bus_spec.baud});
  }
  options.timing = true;
  options.seed = 1;
  sms::simulator::SimulatedBus bus(options);
  start_precise(bus);
  sms::test::TempDir dir;
  const int worst = worst_transaction_ms(bus_spec.baud, response_timeout_ms);
  const int watchdog = worst + 1;
  std::string yaml = "buses:\n  - {name: line, device: \"" + bus.slave_path() +
                     "\", protocol: " + bus_spec.bus_protocol + ", baud: " + std::to_string(bus_spec.baud) +
                     ", response_timeout_ms: " + std::to_string(response_timeout_ms) +
                     ", retries: " + std::to_string(kRetries) + ", watchdog: {timeout_ms: " + std::to_string(watchdog) +
                     ", feed: any_write}}\nservos:\n";
  for (int id = 1; id <= 3; ++id) {
    yaml += "  - {bus: line, id: " + std::to_string(id) + ", table: " + bus_spec.name + "}\n";
  }
  GatewayProcess gateway = GatewayProcess::with_config(dir, yaml, 1, {}, gateway_program());
  for (int id = 1; id <= 3; ++id) sms::test::wait_until_polled(gateway.port(), id);
  for (const int id : {kLate, kOther}) {
    ModbusClient unit(gateway.port(), id);
    for (const Write& write : bus_spec.spin) {
      if (!unit.write_register(write.address, write.value).ok()) throw std::runtime_error("spin write refused");
    }
  }
  bus.set_reply_delay(kLate, std::chrono::milliseconds{late_ms});

  std::atomic<bool> done{false};
  std::atomic<std::uint64_t> hmi_reads{0};
  std::thread hmi([&] {
    ModbusClient reader(gateway.port(), kLate, 15s);
    while (!done.load()) {
      (void)reader.read_holding(bus_spec.read_address, 1);
      hmi_reads.fetch_add(1);
    }
  });
  std::atomic<std::uint32_t> oldest_other_ms{0};
  std::thread watcher([&] {
    ModbusClient facts(gateway.port(), kOther);
    while (!done.load()) {
      const auto age = facts.read_input(kFactCacheAge, 1);
      if (age.ok()) oldest_other_ms = std::max<std::uint32_t>(oldest_other_ms.load(), age.values.at(0));
      std::this_thread::sleep_for(5ms);
    }
  });
  ModbusClient plc(gateway.port(), 1, 15s);
  std::vector<std::uint32_t> write_ns;
  std::uint64_t failed = 0;
  const auto end = Clock::now() + duration;
  for (std::uint16_t i = 0; Clock::now() < end; ++i) {
    const auto sent = Clock::now();
    const auto answer =
        plc.write_register(bus_spec.harmless.address, static_cast<std::uint16_t>(bus_spec.harmless.value + i % 2));
    write_ns.push_back(to_ns(Clock::now() - sent));
    if (!answer.ok()) ++failed;
    std::this_thread::sleep_until(sent + kPlcPeriod);
  }
  done = true;
  hmi.join();
  watcher.join();

  ModbusClient panel(gateway.port(), kGatewayUnit);
  const auto trips = panel.read_input(kBus0Trips, 2).or_throw("trips");
  ModbusClient late_unit(gateway.port(), kLate);
  const auto reason = late_unit.read_input(kFactOfflineReason, 1).or_throw("offline reason").at(0);
  std::uint64_t heartbeat_stops = 0;
  for (const auto& servo : bus.servos()) heartbeat_stops += servo.heartbeat_stops;

  const std::string name = "late_servo." + bus_spec.name + ".timeout_" + std::to_string(response_timeout_ms) +
                           "ms.late_" + std::to_string(late_ms) + "ms";
  const LatencySummary writes = summarize(write_ns);
  print_figure(name + ".watchdog_trips", (trips.at(0) << 16) | trips.at(1), "trips");
  print_latency(name + ".plc_write", writes, LatencyUnit::Ms);
  print_figure(name + ".worst_transaction", worst, "ms");
  print_figure(name + ".plc_writes_failed", static_cast<double>(failed), "writes");
  print_figure(name + ".servo3_cache_age.max", oldest_other_ms.load(), "ms");
  print_figure(name + ".servo2_offline_as_late", reason == kAnswersLate ? 1 : 0, "bool");
  print_figure(name + ".hmi_reads", static_cast<double>(hmi_reads.load()), "reads");
  if (bus_spec.table == TableId::D55d)
    print_figure(name + ".heartbeat_stops", static_cast<double>(heartbeat_stops), "stops");
  if (gateway.stop() != 0) throw std::runtime_error("the gateway did not stop cleanly");
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 5;
  double quick = 0;
  if (const auto exit_status = parse_arguments(
          argc, argv, "what a servo that answers late costs the other servos of its bus (watchdog, writes, polls)",
          {{"seconds", &seconds, "PLC writes per case, in seconds"},
           {"quick", &quick, "1: sts, 20 ms timeout, 50 and 400 ms late only"}})) {
    return *exit_status;
  }
  quiet_logs();
  try {
    print_note(
        "servos 1-3, servo 2 late; PLC writes servo 1 every 20 ms; an HMI reads servo 2 back to back; retries 2; "
        "watchdog = worst transaction + 1 ms");
    const auto duration = std::chrono::milliseconds{static_cast<long>(seconds * 1000)};
    for (const Bus& bus : kBuses) {
      if (quick != 0 && bus.table != TableId::Sts) continue;
      for (const int timeout : {20, 100}) {
        if (quick != 0 && timeout != 20) continue;
        for (const int late : {20, 50, 90, 150, 400}) {
          if (quick != 0 && late != 50 && late != 400) continue;
          run_case(bus, timeout, late, duration);
        }
      }
    }
  } catch (const std::exception& error) {
    std::cerr << "late_servo: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
