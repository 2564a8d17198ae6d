// monitor_overhead: what the bus monitor (gateway/bus/wire_monitor.h, docs/MONITOR.md) costs the
// bus thread.
//   (a) WireMonitor::record() of one 21-byte answer frame, in CPU ns per call (the recording
//       thread's CPU time, so a loaded machine does not inflate it): alone, and while a reader
//       (the console's live view) drains and describes the ring every 10 ms; and the wall-clock
//       read each record makes, alone;
//   (b) the poll cycle of 6 simulated sts servos at 1 000 000 baud (wire timing on, polling back
//       to back) run in-process by the bus engine with and without the tap, in alternating
//       windows: cycles per second and the median cycle the engine reports (wall time), and the
//       process's CPU time per cycle (bus thread and simulated servos: the tap's cost is the
//       difference).
//
//   monitor_overhead [--records N] [--seconds S] [--rounds R]   (defaults 2 000 000, 2 s, 3 rounds)
#include <time.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "bench/bench_support.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/wire_monitor.h"
#include "modbus_map/register_map.h"
#include "modbus_map/tables.h"

namespace {

using namespace sms;
using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServos = 6;

modbus_map::ServoTables sts_tables() {
  modbus_map::ServoTables tables;
  for (std::uint8_t id = 1; id <= kServos; ++id) {
    tables.set(id, modbus_map::table(modbus_map::TableId::Sts), modbus_map::ByteOrder::LowFirst);
  }
  return tables;
}

// An sts answer to the poll cycle's SYNC READ of the 15-byte feedback block.
const protocol::Bytes kAnswer{0xFF, 0xFF, 0x01, 0x11, 0x00, 0x00, 0x08, 0x00, 0x00, 0x00, 0x00,
                              0x79, 0x1E, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x4C};

// CPU time of the calling thread, or of the whole process: what the work costs, whatever else
// runs on the machine (wall time on a loaded machine counts the waits for a CPU too).
double cpu_ns(clockid_t clock) {
  timespec now{};
  ::clock_gettime(clock, &now);
  return static_cast<double>(now.tv_sec) * 1e9 + static_cast<double>(now.tv_nsec);
}

// The wall clock each record reads, alone: part of record()'s cost.
double clock_ns(std::size_t reads) {
  // Unsigned: the sum of nanosecond clock readings wraps, as it may (a signed sum overflows).
  std::uint64_t sink = 0;
  const double start = cpu_ns(CLOCK_THREAD_CPUTIME_ID);
  for (std::size_t i = 0; i < reads; ++i) {
    sink += static_cast<std::uint64_t>(std::chrono::system_clock::now().time_since_epoch().count());
  }
  const double elapsed = cpu_ns(CLOCK_THREAD_CPUTIME_ID) - start;
  if (sink == 42) std::cerr << "";  // keeps the loop
  return elapsed / static_cast<double>(reads);
}

double record_ns(std::size_t records, bool with_reader) {
  auto monitor = std::make_shared<gateway::WireMonitor>("bench", protocol::BusProtocol::Feetech, sts_tables());
  std::atomic<bool> stop{false};
  std::thread reader;
  if (with_reader) {
    reader = std::thread([&] {
      gateway::MonitorReader watcher(monitor);
      while (!stop.load()) {
        (void)watcher.poll(4096);
        std::this_thread::sleep_for(10ms);
      }
    });
  }
  const double start = cpu_ns(CLOCK_THREAD_CPUTIME_ID);
  for (std::size_t i = 0; i < records; ++i) monitor->record(gateway::WireDirection::FromServos, kAnswer);
  const double elapsed = cpu_ns(CLOCK_THREAD_CPUTIME_ID) - start;
  stop = true;
  if (reader.joinable()) reader.join();
  return elapsed / static_cast<double>(records);
}

gateway::BusSettings engine_settings(const std::string& device) {
  gateway::BusSettings settings;
  settings.name = "bench";
  settings.protocol = protocol::BusProtocol::Feetech;
  settings.serial.device = device;
  settings.serial.baud = kBaud;
  settings.response_timeout = 20ms;
  settings.poll_period = 0ms;  // back to back: every cycle is bus work
  const auto block = modbus_map::default_poll_block(modbus_map::TableId::Sts);
  for (std::uint8_t id = 1; id <= kServos; ++id) {
    settings.servos.push_back(
        {id, modbus_map::TableId::Sts, modbus_map::ByteOrder::LowFirst, {block.address, block.count}});
  }
  return settings;
}

struct CycleFigures {
  double cycles_per_s = 0;
  double median_cycle_us = 0;
  double cpu_us_per_cycle = 0;   // the whole process (bus thread and simulated servos) per cycle
  double records_per_cycle = 0;  // with the tap: records the bus thread made per cycle
};

CycleFigures measure_cycles(const std::string& device, bool tapped, std::chrono::milliseconds duration) {
  auto settings = engine_settings(device);
  std::shared_ptr<gateway::WireMonitor> monitor;
  if (tapped) {
    monitor = gateway::WireMonitor::for_bus(settings);
    settings.wire_monitor = monitor;
  }
  auto engine = gateway::make_bus_engine(std::move(settings), {});
  engine->start();
  const auto ready_by = Clock::now() + 5s;
  while (!engine->discovered() && Clock::now() < ready_by) std::this_thread::sleep_for(5ms);
  std::this_thread::sleep_for(200ms);  // past discovery's identity reads
  std::vector<std::uint32_t> cycle_us;
  const auto first = engine->counters();
  const double cpu_start = cpu_ns(CLOCK_PROCESS_CPUTIME_ID);
  const std::uint64_t records_start = monitor ? monitor->next_sequence() : 0;
  const auto start = Clock::now();
  while (Clock::now() - start < duration) {
    std::this_thread::sleep_for(10ms);
    cycle_us.push_back(engine->counters().last_poll_cycle_us);
  }
  const auto last = engine->counters();
  const double cpu = cpu_ns(CLOCK_PROCESS_CPUTIME_ID) - cpu_start;
  const std::uint64_t records = monitor ? monitor->next_sequence() - records_start : 0;
  const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
  engine->stop();
  std::sort(cycle_us.begin(), cycle_us.end());
  const auto cycles = static_cast<double>(last.poll_cycles - first.poll_cycles);
  return {cycles / seconds, cycle_us.empty() ? 0.0 : static_cast<double>(cycle_us[cycle_us.size() / 2]),
          cycles > 0 ? cpu / 1000.0 / cycles : 0.0, cycles > 0 ? static_cast<double>(records) / cycles : 0.0};
}

}  // namespace

int main(int argc, char** argv) {
  spdlog::set_level(spdlog::level::warn);  // no discovery summaries between the figures
  double records_arg = 2'000'000;
  double seconds_arg = 2;
  double rounds_arg = 3;
  if (const auto exit_status =
          parse_arguments(argc, argv, "the bus monitor's cost: a record, a poll cycle with and without it",
                          {{"records", &records_arg, "frames recorded per figure of (a)"},
                           {"seconds", &seconds_arg, "seconds per poll-cycle figure of (b)"},
                           {"rounds", &rounds_arg, "rounds of (b)"}})) {
    return *exit_status;
  }
  const auto records = static_cast<std::size_t>(records_arg);
  const auto seconds = static_cast<int>(seconds_arg);
  const auto rounds = static_cast<int>(rounds_arg);
  print_note("(a) WireMonitor::record of a 21-byte frame");
  print_figure("monitor.clock_ns", clock_ns(records), "ns");
  print_figure("monitor.record_ns", record_ns(records, false), "ns");
  print_figure("monitor.record_ns_while_read", record_ns(records, true), "ns");

  print_note("(b) poll cycle, 6 sts servos, 1 000 000 baud, back to back, in-process engine");
  simulator::SimulatedBus bus(sts_bus(kServos));
  start_precise(bus);
  set_return_delay(bus, kServos, kStsFastestReturnDelay);
  const auto window = std::chrono::milliseconds{seconds * 1000};
  CycleFigures without{}, with{};
  for (int round = 0; round < rounds; ++round) {
    const auto off = measure_cycles(bus.slave_path(), false, window);
    const auto on = measure_cycles(bus.slave_path(), true, window);
    without.cycles_per_s += off.cycles_per_s / rounds;
    without.median_cycle_us += off.median_cycle_us / rounds;
    with.cycles_per_s += on.cycles_per_s / rounds;
    with.median_cycle_us += on.median_cycle_us / rounds;
    without.cpu_us_per_cycle += off.cpu_us_per_cycle / rounds;
    with.cpu_us_per_cycle += on.cpu_us_per_cycle / rounds;
    with.records_per_cycle += on.records_per_cycle / rounds;
  }
  print_figure("monitor.poll_cycle.without_tap.cycles_per_s", without.cycles_per_s, "1/s");
  print_figure("monitor.poll_cycle.with_tap.cycles_per_s", with.cycles_per_s, "1/s");
  print_figure("monitor.poll_cycle.without_tap.median_cycle", without.median_cycle_us, "us");
  print_figure("monitor.poll_cycle.with_tap.median_cycle", with.median_cycle_us, "us");
  print_figure("monitor.poll_cycle.without_tap.cpu_per_cycle", without.cpu_us_per_cycle, "us");
  print_figure("monitor.poll_cycle.with_tap.cpu_per_cycle", with.cpu_us_per_cycle, "us");
  print_figure("monitor.poll_cycle.with_tap.records_per_cycle", with.records_per_cycle, "records");
  bus.stop();
  return 0;
}
