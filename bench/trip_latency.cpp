// trip_latency: watchdog trip latency — last feed (a client's last Modbus write) to the safe stop's SYNC WRITE on the
// simulated wire, 6 and 60 sts servos at 1 Mbaud, timed by the simulator's frame observer.
//
//   trip_latency [--rounds 30] [--timeout-ms 200] [--servos N] [--quick]
//
// docs/PLC_GUIDE.md "Safety". The real sms-gateway runs as a child process (bench_support) on a
// simulated bus in this process (sts servos, 1 000 000 baud, wire timing on, return delay 100 us: the sts floor), its
// bus configured `watchdog: {timeout_ms: T, feed: any_write}`. Each round a client writes
// operating_mode (33) := 1 and goal_speed (46) := 1000 to every servo (the servos turn), then goes
// silent: the time it sent its last write is the last feed (the gateway counts from that write's
// arrival). The simulator reports every request frame it decodes with its time on the modelled
// wire (SimulatedBus::set_frame_observer): the stop has landed when the SYNC WRITE frames sent
// after the last feed have named every servo, at the end of the last one on the wire. Latency =
// that instant - the last feed; "beyond" subtracts the timeout. It splits into "wake" (timeout
// expiry -> the stop's first READ reaches the bus: the watchdog timer, the hand-over to the bus
// engine, a poll transaction already on the wire) and "stop" (first READ -> last stop frame's end:
// one READ per servo of what a hold needs, then the SYNC WRITE frames); "wire floor" is the wire
// time of exactly those frames and their replies. Also counted: poll SYNC READs the engine ran
// inside the stop (between its READs, or between the last READ and the first SYNC WRITE) and the
// gap from the last READ's reply to the first SYNC WRITE. Each round then checks that every servo's
// goal_speed reads 0, reads the gateway's own figure (unit 255 input registers 116-117: last feed
// -> its engine finished the stop frames) and re-arms (unit 255 coil 2 := 0). Everything talks to
// 127.0.0.1, the rounds are bounded (and each bus size by kSizeTimeLimit) and it stops by itself.
#include <modbus/modbus.h>

#include <algorithm>
#include <cerrno>
#include <condition_variable>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <iterator>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServoCounts[] = {6, 60};
constexpr int kModeAddress = 33;       // sts operating_mode
constexpr int kGoalSpeedAddress = 46;  // sts goal_speed
constexpr std::uint16_t kSpeedMode = 1;
constexpr std::uint16_t kGoalSpeed = 1000;
constexpr int kWatchdogCoil = 2;           // gateway unit: write 0 re-arms every tripped watchdog
constexpr int kBusSafetyBlock = 110;       // bus 0: 100 + 20 * 0 + 10 ...
constexpr std::size_t kStateOffset = 0;    // 110 watchdog state
constexpr std::size_t kTripsOffset = 2;    // 112-113 trips
constexpr std::size_t kCauseOffset = 5;    // 115 cause of the last safe stop
constexpr std::size_t kLatencyOffset = 6;  // 116-117 its latency, µs
constexpr int kSafetyRegisters = 8;
constexpr std::uint16_t kTripped = 3;
constexpr std::uint16_t kCauseWatchdog = 1;
constexpr unsigned kQuickRounds = 8;
constexpr auto kSizeTimeLimit = 120s;    // per bus size, whatever --rounds says
constexpr std::size_t kStatusBytes = 6;  // FF FF id len error chk around a reply's data

using sms::protocol::common::kRead;
using sms::protocol::common::kSyncWrite;
using sms::protocol::feetech::kSyncRead;

// What the simulator heard: stop READs, stop SYNC WRITEs, poll SYNC READs (the client's WRITEs
// are left out).
struct Frame {
  Clock::time_point arrived;
  Clock::time_point wire_end;
  std::uint8_t code = 0;
  sms::protocol::Bytes params;
};

class FrameLog {
 public:
  // Bus thread, under the bus's lock.
  void record(const sms::simulator::ReceivedFrame& frame) {
    if (frame.code != kRead && frame.code != kSyncWrite && frame.code != kSyncRead) return;
    {
      std::lock_guard lock(mutex_);
      frames_.push_back(Frame{frame.arrived, frame.wire_end, frame.code, frame.params});
    }
    changed_.notify_all();
  }
  void clear() {
    std::lock_guard lock(mutex_);
    frames_.clear();
  }
  // Waits until the SYNC WRITE frames that arrived after `after` name every ID 1..servos; then
  // the frames from `after` to that one. nullopt at `deadline`.
  std::optional<std::vector<Frame>> wait_stop(Clock::time_point after, unsigned servos, Clock::time_point deadline) {
    std::unique_lock lock(mutex_);
    std::optional<std::vector<Frame>> stop;
    changed_.wait_until(lock, deadline, [&] {
      std::set<std::uint8_t> named;
      for (std::size_t i = 0; i < frames_.size(); ++i) {
        const Frame& frame = frames_[i];
        if (frame.arrived < after || frame.code != kSyncWrite) continue;
        if (const auto sync = sms::protocol::parse_sync_write(frame.params)) {
          for (const auto& entry : sync->entries) {
            if (entry.id >= 1 && entry.id <= servos) named.insert(entry.id);
          }
        }
        if (named.size() == servos) {
          stop.emplace();
          for (std::size_t j = 0; j <= i; ++j) {
            if (frames_[j].arrived >= after) stop->push_back(frames_[j]);
          }
          return true;
        }
      }
      return false;
    });
    return stop;
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<Frame> frames_;
};

// A round's set-up that did not go through: a write refused with 0x04 (the watchdog tripped while
// the round was being set up: a loaded machine can hold the client longer than the timeout
// between two writes), a servo that kept missing the gateway's response timeout (0x0B: a
// loaded machine can hold the simulator), or an answer later than the client's 3 s (seen at a
// load average of 8 beside the test command's builds). The round is set up again; the figures
// are about the stop, not the set-up.
struct SetupTripped {};

void write_or_throw(modbus_t* context, int unit, int address, std::uint16_t value) {
  modbus_set_slave(context, unit);
  int attempts = 5;
  int written = 0;
  while ((written = modbus_write_register(context, address, value)) != 1 && errno == EMBXGTAR && --attempts > 0) {
    std::this_thread::sleep_for(10ms);  // lets a starved simulator catch up
  }
  if (written != 1) {
    if (errno == ETIMEDOUT) {
      // Its answer may still come: a new connection, so that it is not taken for the next one's
      // (libmodbus then says "Invalid data", as the re-arm did once).
      modbus_close(context);
      if (modbus_connect(context) != 0) throw std::runtime_error("reconnect after a timeout: " + modbus_error_text());
      throw SetupTripped{};
    }
    if (errno == EMBXSFAIL || errno == EMBXGTAR) throw SetupTripped{};
    throw std::runtime_error("unit " + std::to_string(unit) + ": FC06 " + std::to_string(address) +
                             " := " + std::to_string(value) + " failed: " + modbus_error_text());
  }
}

bool all_stopped(sms::simulator::SimulatedBus& bus, unsigned servos) {
  for (unsigned id = 1; id <= servos; ++id) {
    if (bus.read_field(static_cast<std::uint8_t>(id), "goal_speed").value_or(1) != 0) return false;
  }
  return true;
}

struct SizeResult {
  unsigned servos = 0;
  std::chrono::milliseconds timeout{0};
  unsigned missed = 0;                 // no complete stop seen in time
  unsigned not_stopped = 0;            // the frames came but a servo's goal_speed was not 0
  unsigned setup_tripped = 0;          // rounds set up again: a trip or a kept 0x0B during the set-up
  unsigned no_figure = 0;              // the gateway's register did not show this round's stop
  std::size_t polls_in_reads = 0;      // poll SYNC READs between the stop's first and last READ
  std::size_t polls_before_write = 0;  // ... between its last READ and its first SYNC WRITE
  LatencySummary total, beyond, wake, stop, reported, wire_floor, write_gap;
  std::optional<double> bench_minus_gateway_us;  // median per round: this bench's figure - the gateway's
};

double ms(double us) { return us / 1000.0; }

SizeResult measure(unsigned servos, unsigned rounds, std::chrono::milliseconds timeout) {
  FrameLog log;  // outlives the bus, whose thread calls it
  sms::simulator::SimulatedBus bus(sts_bus(servos));
  start_precise(bus);
  set_return_delay(bus, servos, kStsFastestReturnDelay);
  bus.set_frame_observer([&log](const sms::simulator::ReceivedFrame& frame) { log.record(frame); });
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = servos;
  setup.watchdog = timeout;
  BenchGateway gateway(setup);
  gateway.wait_ready(servos);
  ModbusClient client(gateway.port(), kGatewayUnit);
  ModbusClient facts_client(gateway.port(), kGatewayUnit);

  const auto safety_registers = [&] {
    return facts_client.read_input(kBusSafetyBlock, kSafetyRegisters).or_throw("FC04 unit 255, bus safety block");
  };
  auto registers = safety_registers();
  std::uint32_t trips_seen = u32(registers[kTripsOffset], registers[kTripsOffset + 1]);
  std::uint32_t previous_figure = u32(registers[kLatencyOffset], registers[kLatencyOffset + 1]);

  SizeResult result;
  result.servos = servos;
  result.timeout = timeout;
  std::vector<std::uint32_t> total_ns, beyond_ns, wake_ns, stop_ns, reported_ns, floor_ns, gap_ns;
  std::vector<double> difference_us;
  const auto size_deadline = Clock::now() + kSizeTimeLimit;
  for (unsigned round = 0; round < rounds && Clock::now() < size_deadline; ++round) {
    modbus_set_slave(client.context(), kGatewayUnit);
    for (int attempt = 1; modbus_write_bit(client.context(), kWatchdogCoil, 0) != 1; ++attempt) {
      // An answer later than the client's 3 s (a loaded machine): asked again on a new connection,
      // at most 3 times.
      if (errno != ETIMEDOUT || attempt == 3) {
        throw std::runtime_error("re-arm (unit 255 coil 2 := 0): " + modbus_error_text());
      }
      modbus_close(client.context());
      if (modbus_connect(client.context()) != 0) throw std::runtime_error("reconnect: " + modbus_error_text());
    }
    log.clear();
    Clock::time_point last_feed;
    try {
      for (unsigned id = 1; id <= servos; ++id)
        write_or_throw(client.context(), static_cast<int>(id), kModeAddress, kSpeedMode);
      for (unsigned id = 1; id <= servos; ++id) {
        last_feed = Clock::now();  // sent now; the gateway's count starts at its arrival
        write_or_throw(client.context(), static_cast<int>(id), kGoalSpeedAddress, kGoalSpeed);
      }
    } catch (const SetupTripped&) {
      // Not a round: wait for that trip's stop to be recorded, then set the round up again.
      ++result.setup_tripped;
      if (result.setup_tripped > 3 * rounds) {
        throw std::runtime_error(
            "every set-up failed: the watchdog tripped (0x04) or a servo kept missing the "
            "response timeout (0x0B) while the round was being set up");
      }
      std::this_thread::sleep_for(timeout);
      registers = safety_registers();
      trips_seen = u32(registers[kTripsOffset], registers[kTripsOffset + 1]);
      previous_figure = u32(registers[kLatencyOffset], registers[kLatencyOffset + 1]);
      --round;
      continue;
    }
    const auto frames = log.wait_stop(last_feed, servos, last_feed + timeout + 5s);
    if (!frames) {
      ++result.missed;
      continue;
    }
    const Frame& end = frames->back();
    const auto first_read =
        std::find_if(frames->begin(), frames->end(), [](const Frame& f) { return f.code == kRead; });
    const Clock::time_point stop_start = first_read != frames->end() ? first_read->arrived : end.arrived;
    const Clock::time_point deadline = last_feed + timeout;
    // The last stop READ's reply has left the wire at `reads_end` (the reply's frames carry their
    // return delay already); the first SYNC WRITE follows the safety thread's hand-over of the
    // write phase to the bus engine. The floor counts each READ's return delay (100 us).
    std::size_t floor_bytes = 0;
    double floor_extra_us = 0;
    std::optional<Clock::time_point> reads_end;
    std::optional<Clock::time_point> first_write;
    std::size_t polls = 0;
    for (auto frame = frames->begin(); frame != frames->end(); ++frame) {
      if (frame->arrived < stop_start) continue;
      if (frame->code == kSyncRead) {
        ++polls;
        continue;
      }
      floor_bytes += kStatusBytes + frame->params.size();  // the request
      if (frame->code == kRead && frame->params.size() == 2) {
        const std::size_t reply = kStatusBytes + frame->params[1];
        floor_bytes += reply;
        floor_extra_us += kStsFastestReturnDelayUs;
        reads_end = frame->wire_end + std::chrono::microseconds(static_cast<long>(wire_us(reply)));
        result.polls_in_reads += polls;
        polls = 0;
      }
      if (frame->code == kSyncWrite && !first_write) {
        first_write = frame->arrived;
        result.polls_before_write += polls;
        polls = 0;
      }
    }
    if (reads_end && first_write) gap_ns.push_back(to_ns(std::max(*first_write - *reads_end, Clock::duration::zero())));
    total_ns.push_back(to_ns(end.wire_end - last_feed));
    beyond_ns.push_back(to_ns(std::max(end.wire_end - deadline, Clock::duration::zero())));
    wake_ns.push_back(to_ns(std::max(stop_start - deadline, Clock::duration::zero())));
    stop_ns.push_back(to_ns(end.wire_end - stop_start));
    floor_ns.push_back(static_cast<std::uint32_t>((wire_us(floor_bytes) + floor_extra_us) * 1000.0));
    if (!all_stopped(bus, servos)) ++result.not_stopped;

    // The gateway's own figure: stored when its engine has finished the stop frames.
    const auto figure_deadline = Clock::now() + 1s;
    bool seen = false;
    for (;;) {
      registers = safety_registers();
      const std::uint32_t trips = u32(registers[kTripsOffset], registers[kTripsOffset + 1]);
      const std::uint32_t figure = u32(registers[kLatencyOffset], registers[kLatencyOffset + 1]);
      if (registers[kStateOffset] == kTripped && trips > trips_seen && registers[kCauseOffset] == kCauseWatchdog &&
          figure != previous_figure) {
        reported_ns.push_back(figure * 1000u);
        difference_us.push_back(static_cast<double>(total_ns.back()) / 1000.0 - figure);
        trips_seen = trips;
        previous_figure = figure;
        seen = true;
        break;
      }
      if (Clock::now() > figure_deadline) break;
      std::this_thread::sleep_for(1ms);
    }
    if (!seen) {
      ++result.no_figure;
      trips_seen = u32(registers[kTripsOffset], registers[kTripsOffset + 1]);
      previous_figure = u32(registers[kLatencyOffset], registers[kLatencyOffset + 1]);
    }
  }
  bus.set_frame_observer({});
  gateway.stop();
  result.total = summarize(total_ns);
  result.beyond = summarize(beyond_ns);
  result.wake = summarize(wake_ns);
  result.stop = summarize(stop_ns);
  result.reported = summarize(reported_ns);
  result.wire_floor = summarize(floor_ns);
  result.write_gap = summarize(gap_ns);
  if (!difference_us.empty()) {
    std::sort(difference_us.begin(), difference_us.end());
    result.bench_minus_gateway_us = difference_us[(difference_us.size() - 1) / 2];
  }

  const std::string name = "trip_latency.servos_" + std::to_string(servos);
  print_figure(name + ".timeout", static_cast<double>(timeout.count()), "ms");
  print_figure(name + ".rounds", static_cast<double>(result.total.count), "");
  print_figure(name + ".missed", result.missed, "");
  print_figure(name + ".not_stopped", result.not_stopped, "");
  print_figure(name + ".setup_tripped", result.setup_tripped, "");
  print_latency(name + ".last_feed_to_stop_frame", result.total, LatencyUnit::Ms);
  print_latency(name + ".beyond_timeout", result.beyond, LatencyUnit::Ms, false);
  print_latency(name + ".wake", result.wake, LatencyUnit::Ms, false);
  print_latency(name + ".stop", result.stop, LatencyUnit::Ms, false);
  print_figure(name + ".stop_wire_floor", ms(result.wire_floor.p50_us), "ms");
  print_latency(name + ".last_read_to_first_sync_write", result.write_gap, LatencyUnit::Ms, false);
  print_figure(name + ".polls_between_stop_reads", static_cast<double>(result.polls_in_reads), "");
  print_figure(name + ".polls_between_reads_and_sync_write", static_cast<double>(result.polls_before_write), "");
  print_latency(name + ".gateway_reported", result.reported, LatencyUnit::Ms, false);
  print_figure(name + ".gateway_reported.rounds", static_cast<double>(result.reported.count), "");
  if (result.bench_minus_gateway_us)
    print_figure(name + ".bench_minus_gateway.p50", *result.bench_minus_gateway_us, "us");
  return result;
}

std::string fixed(double value, int decimals = 1) {
  char text[32];
  std::snprintf(text, sizeof text, "%.*f", decimals, value);
  return text;
}

void print_table(const std::vector<SizeResult>& results) {
  char line[320];
  print_note("");
  print_note(
      "servos | timeout | rounds | last feed -> stop frame p50 / p99 / max | beyond timeout p50 / p99 | "
      "wake p50 | stop p50 (wire floor) | reads -> write gap p50 / p99, polls in the stop | gateway-reported p50 / "
      "p99");
  for (const SizeResult& r : results) {
    std::snprintf(
        line, sizeof line,
        "%6u | %4lld ms | %6zu | %8s / %s / %s ms | %6s / %s ms | %5s ms | %5s ms (%s) | %s / %s ms, %zu | %s / %s ms",
        r.servos, static_cast<long long>(r.timeout.count()), r.total.count, fixed(ms(r.total.p50_us)).c_str(),
        fixed(ms(r.total.p99_us)).c_str(), fixed(ms(r.total.max_us)).c_str(), fixed(ms(r.beyond.p50_us)).c_str(),
        fixed(ms(r.beyond.p99_us)).c_str(), fixed(ms(r.wake.p50_us), 2).c_str(), fixed(ms(r.stop.p50_us)).c_str(),
        fixed(ms(r.wire_floor.p50_us)).c_str(), fixed(ms(r.write_gap.p50_us), 2).c_str(),
        fixed(ms(r.write_gap.p99_us), 2).c_str(), r.polls_in_reads + r.polls_before_write,
        fixed(ms(r.reported.p50_us)).c_str(), fixed(ms(r.reported.p99_us)).c_str());
    print_note(line);
  }
}

}  // namespace

int main(int argc, char** argv) {
  double rounds = 30;
  double timeout_ms = 200;  // longer than the bus's worst transaction (156 ms here), as --check-config demands
  double only_servos = 0;
  // --quick (no value) is taken out before the `--name value` options are parsed.
  bool quick = false;
  std::vector<char*> arguments;
  for (int i = 0; i < argc; ++i) {
    if (i > 0 && std::strcmp(argv[i], "--quick") == 0) {
      quick = true;
    } else {
      arguments.push_back(argv[i]);
    }
  }
  if (const auto exit_status =
          parse_arguments(static_cast<int>(arguments.size()), arguments.data(),
                          "watchdog trip latency (last feed -> stop frame on the wire) for 6 and 60 servos at 1 Mbaud; "
                          "--quick: " +
                              std::to_string(kQuickRounds) + " rounds per size",
                          {{"rounds", &rounds, "trips per bus size"},
                           {"timeout-ms", &timeout_ms, "the watchdog timeout"},
                           {"servos", &only_servos, "only a bus of this many servos, 1-253 (0: 6 and 60)"}})) {
    return *exit_status;
  }
  if (quick) rounds = std::min<double>(rounds, kQuickRounds);
  if (rounds < 1 || timeout_ms < 10 || only_servos > 253) {
    std::cerr << "trip_latency: --rounds must be at least 1, --timeout-ms at least 10, --servos at most 253\n";
    return 2;
  }
  try {
    quiet_logs();
    double load[3] = {0, 0, 0};
    if (getloadavg(load, 3) == 3) {
      print_figure("load_average_1min", load[0], "");
      print_note("load average " + fixed(load[0], 2) + " " + fixed(load[1], 2) + " " + fixed(load[2], 2));
    }
    print_note(
        "sms-gateway child, sts servos at 1 Mbaud with wire timing, watchdog any_write; each round a client "
        "sets every servo turning, then goes silent; stop frame = end on the simulated wire of the SYNC WRITE "
        "that completes the stop (simulator frame observer); gateway_reported = unit 255 input registers 116-117");
    std::vector<unsigned> sizes(std::begin(kServoCounts), std::end(kServoCounts));
    if (only_servos > 0) sizes = {static_cast<unsigned>(only_servos)};
    std::vector<SizeResult> results;
    for (const unsigned servos : sizes) {
      results.push_back(
          measure(servos, static_cast<unsigned>(rounds), std::chrono::milliseconds(static_cast<long>(timeout_ms))));
    }
    if (getloadavg(load, 3) == 3) print_figure("load_average_1min_after", load[0], "");
    print_table(results);
  } catch (const std::exception& error) {
    std::cerr << "trip_latency: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
