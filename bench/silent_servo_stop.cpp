// silent_servo_stop: a watchdog stop and live writes on a bus where one servo is silent.
//
//   silent_servo_stop [--trials 10] [--timeouts 200,1000] [--quick]
//
// docs/SAFETY.md "How long a stop can take": a watchdog stop leaves at most timeout_ms + one
// transaction (config::worst_transaction) + its frames after the last feed, and a servo known to
// be silent costs its bus one attempt per probe period. Here: sts servos 1-3 at 1 Mbaud on a bus
// simulated in this process (wire timing on), servo 3 offline from the start, the real sms-gateway
// as a child process with `response_timeout_ms` R, `retries: 2` and a watchdog of the shortest
// timeout --check-config accepts (the worst transaction + 1 ms). Each trial a PLC-like client
// re-arms the watchdog, writes servo 1's goal position every 200 ms (8 writes, timing each), then
// goes silent: the stop has landed when a SYNC WRITE naming servo 1 ends on the simulated wire
// (the simulator's frame observer). Printed per R: the stop's delay after the last feed against
// the bound, how many trials stayed inside it, the live writes' latency, and the attempts the
// silent servo cost (frames addressed to it per probe period). Talks to 127.0.0.1 only, bounded.
#include <modbus/modbus.h>

#include <algorithm>
#include <condition_variable>
#include <cstring>
#include <iostream>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"
#include "config/config.h"
#include "protocol/instructions.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServos = 3;
constexpr std::uint8_t kSilent = 3;
constexpr std::uint8_t kLive = 1;
constexpr int kGoalPosition = 42;     // sts goal_position
constexpr int kWatchdogCoil = 2;      // unit 255: 0 re-arms every tripped watchdog
constexpr int kBusSafetyBlock = 110;  // unit 255, bus 0: state, ..., trips (112-113), latency (116-117)
constexpr int kWrites = 8;
constexpr auto kWritePeriod = 200ms;
constexpr auto kProbePeriod = 1000ms;

// What the simulator heard: SYNC WRITEs naming servo 1, and every frame addressed to servo 3.
class Wire {
 public:
  void record(const sms::simulator::ReceivedFrame& frame) {
    std::lock_guard lock(mutex_);
    if (frame.id == kSilent) to_silent_.push_back(frame.arrived);
    if (frame.code != sms::protocol::common::kSyncWrite) return;
    if (const auto sync = sms::protocol::parse_sync_write(frame.params)) {
      for (const auto& entry : sync->entries) {
        if (entry.id == kLive) stops_.push_back(frame.wire_end);
      }
    }
    changed_.notify_all();
  }
  // The end of the first SYNC WRITE naming servo 1 that arrived after `after`.
  std::optional<Clock::time_point> wait_stop(Clock::time_point after, Clock::time_point deadline) {
    std::unique_lock lock(mutex_);
    std::optional<Clock::time_point> found;
    changed_.wait_until(lock, deadline, [&] {
      for (const auto end : stops_) {
        if (end > after) {
          found = end;
          return true;
        }
      }
      return false;
    });
    return found;
  }
  std::size_t frames_to_silent_since(Clock::time_point since) {
    std::lock_guard lock(mutex_);
    return static_cast<std::size_t>(
        std::count_if(to_silent_.begin(), to_silent_.end(), [&](Clock::time_point at) { return at >= since; }));
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<Clock::time_point> stops_;
  std::vector<Clock::time_point> to_silent_;
};

// p50, p99 and max of `samples` (ms).
void print_ms(const std::string& name, std::vector<double> samples) {
  if (samples.empty()) return;
  std::sort(samples.begin(), samples.end());
  const auto at = [&](double quantile) {
    return samples[static_cast<std::size_t>(quantile * static_cast<double>(samples.size() - 1))];
  };
  print_figure(name + ".p50", at(0.5), "ms");
  print_figure(name + ".p99", at(0.99), "ms");
  print_figure(name + ".max", samples.back(), "ms");
}

std::chrono::milliseconds worst_transaction(std::chrono::milliseconds response_timeout, unsigned retries) {
  sms::config::BusConfig bus;
  bus.baud = kBaud;
  bus.response_timeout = response_timeout;
  bus.retries = retries;
  return sms::config::worst_transaction(bus);
}

void measure(std::chrono::milliseconds response_timeout, unsigned trials) {
  constexpr unsigned kRetries = 2;
  const auto worst = worst_transaction(response_timeout, kRetries);
  const auto watchdog = worst + 1ms;
  // The stop's frames: its SYNC READ of the servos' state and the SYNC WRITE, a few ms at most.
  const auto bound = watchdog + worst + 5ms;
  Wire wire;  // outlives the bus, whose thread calls it
  sms::simulator::SimulatedBus bus(sts_bus(kServos));
  start_precise(bus);
  set_return_delay(bus, kServos, kStsFastestReturnDelay);
  bus.set_offline(kSilent, true);
  bus.set_frame_observer([&wire](const sms::simulator::ReceivedFrame& frame) { wire.record(frame); });
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = kServos;
  setup.response_timeout = response_timeout;
  setup.retries = kRetries;
  setup.probe_period = kProbePeriod;
  setup.watchdog = watchdog;
  BenchGateway gateway(setup);
  gateway.wait_ready(kServos - 1);
  ModbusClient plc(gateway.port(), kLive, std::chrono::seconds{30});

  // Milliseconds: a stop comes seconds after the last feed, beyond what 32-bit nanoseconds hold.
  std::vector<double> write_ms;
  std::vector<double> stop_ms;
  std::vector<double> reported_ms;
  std::uint32_t trips_seen = 0;
  unsigned inside = 0;
  unsigned missed = 0;
  unsigned write_errors = 0;
  std::string first_error;
  const auto started = Clock::now();
  for (unsigned trial = 0; trial < trials; ++trial) {
    modbus_set_slave(plc.context(), kGatewayUnit);
    if (modbus_write_bit(plc.context(), kWatchdogCoil, 0) != 1) {
      throw std::runtime_error("re-arm (unit 255 coil 2 := 0): " + modbus_error_text());
    }
    modbus_set_slave(plc.context(), kLive);
    Clock::time_point last_feed;
    for (int i = 0; i < kWrites; ++i) {
      const auto sent = Clock::now();
      const auto value = static_cast<std::uint16_t>(1000 + (i % 2) * 1000);
      if (modbus_write_register(plc.context(), kGoalPosition, value) == 1) {
        last_feed = sent;
        write_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - sent).count());
      } else {
        ++write_errors;
        if (first_error.empty()) first_error = modbus_error_text();
      }
      std::this_thread::sleep_until(sent + kWritePeriod);
    }
    // No stop of this trial can come before the watchdog expires: a SYNC WRITE before that is an
    // earlier stop's (the start-up stop's, or the previous trial's) landing late.
    const auto stop = wire.wait_stop(last_feed + watchdog - 1ms, last_feed + bound + 10s);
    if (!stop) {
      ++missed;
      continue;
    }
    const auto took = *stop - last_feed;
    stop_ms.push_back(std::chrono::duration<double, std::milli>(took).count());
    if (took <= bound) ++inside;
    // The gateway's own figure (unit 255, bus 0: input registers 116-117, µs from the last feed
    // to the stop's frames): read once it shows this trial's trip.
    ModbusClient facts(gateway.port(), kGatewayUnit);
    const auto deadline = Clock::now() + 2s;
    while (Clock::now() < deadline) {
      const auto registers = facts.read_input(kBusSafetyBlock, 8);
      if (registers.ok() && u32(registers.values[2], registers.values[3]) > trips_seen) {
        trips_seen = u32(registers.values[2], registers.values[3]);
        reported_ms.push_back(u32(registers.values[6], registers.values[7]) / 1000.0);
        break;
      }
      std::this_thread::sleep_for(5ms);
    }
  }
  const auto elapsed = Clock::now() - started;
  const double probe_periods = std::chrono::duration<double>(elapsed) / kProbePeriod;
  const auto to_silent = wire.frames_to_silent_since(started);
  bus.set_frame_observer({});
  gateway.stop();

  const std::string name = "silent_servo_stop.timeout_" + std::to_string(response_timeout.count()) + "ms";
  print_figure(name + ".watchdog", static_cast<double>(watchdog.count()), "ms");
  print_figure(name + ".bound", static_cast<double>(bound.count()), "ms");
  print_figure(name + ".trials", static_cast<double>(stop_ms.size()), "");
  print_figure(name + ".inside_bound", inside, "");
  print_figure(name + ".missed", missed, "");
  print_ms(name + ".last_feed_to_stop", stop_ms);
  print_ms(name + ".gateway_reported", reported_ms);
  print_ms(name + ".live_write", write_ms);
  print_figure(name + ".live_write_errors", write_errors, "");
  if (!first_error.empty()) print_note("first write error: " + first_error);
  print_figure(name + ".frames_to_silent_servo_per_probe_period", static_cast<double>(to_silent) / probe_periods, "");
}

std::vector<std::chrono::milliseconds> parse_timeouts(const std::string& text) {
  std::vector<std::chrono::milliseconds> timeouts;
  std::stringstream list(text);
  std::string item;
  while (std::getline(list, item, ',')) timeouts.emplace_back(std::stoi(item));
  return timeouts;
}

}  // namespace

int main(int argc, char** argv) {
  unsigned trials = 10;
  std::vector<std::chrono::milliseconds> timeouts{200ms, 1000ms};
  for (int i = 1; i < argc; ++i) {
    const std::string argument = argv[i];
    if (argument == "--quick") {
      trials = 2;
      timeouts = {200ms};
    } else if (argument == "--trials" && i + 1 < argc) {
      trials = static_cast<unsigned>(std::stoul(argv[++i]));
    } else if (argument == "--timeouts" && i + 1 < argc) {
      timeouts = parse_timeouts(argv[++i]);
    } else {
      const bool help = argument == "--help" || argument == "-h";
      (help ? std::cout : std::cerr) << "usage: silent_servo_stop [--trials N] [--timeouts MS,MS] [--quick]\n";
      return help ? 0 : 2;
    }
  }
  try {
    print_note("sts 1-3 at 1 Mbaud, servo 3 offline, retries 2, watchdog = worst transaction + 1 ms, writes every " +
               std::to_string(kWritePeriod.count()) + " ms");
    for (const auto timeout : timeouts) measure(timeout, trials);
  } catch (const std::exception& error) {
    std::cerr << "silent_servo_stop: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
