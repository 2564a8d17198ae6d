// soak: 16 clients mixing FC03/FC04/FC06/FC16 against the gateway for a minute, sampling the
// gateway process's resident memory every second; at the end, every acknowledged write is read
// back ("A 60-second soak with 16 clients mixing reads and writes shows flat memory").
//
//   soak [--seconds 60]
//
// The gateway (sms-gateway, a child process, so its RSS is its own) drives 6 simulated sts
// servos at 1 Mbaud with their factory return delay (0: 100 us, the sts floor); the simulator runs in this process.
// Each client owns registers nobody else writes — client k: unit 1 + k % 6, slot k / 6:
//   slot 0: FC06 acceleration (41);  FC16 41..42 acceleration, goal position
//   slot 1: FC06 goal speed (46);    FC16 44..46 goal time, (45: second byte of 44), goal speed
//   slot 2: FC06 torque limit (48);  FC16 48 torque limit
// and remembers the last value the gateway acknowledged for each. Reads: FC04 (cache) and FC03
// (live) of the feedback block 56+15. Mix per request: 35 % FC04, 25 % FC03, 20 % FC06, 20 % FC16.
#include <algorithm>
#include <array>
#include <atomic>
#include <iostream>
#include <map>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <modbus/modbus.h>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServos = 6;
constexpr unsigned kClients = 16;
constexpr std::size_t kRequestKinds = 4;
const char* const kRequestNames[kRequestKinds] = {"fc04", "fc03", "fc06", "fc16"};

struct OwnedField {
  std::uint16_t address;
  const char* name;   // modbus_map field name, for the check against the simulator's memory
  std::uint16_t max;  // values written stay in 0..max (inside every field's range)
};
struct Slot {
  OwnedField single;              // FC06 target
  std::uint16_t block_start;      // FC16 block
  std::vector<OwnedField> block;  // fields in the block (their first addresses)
  std::uint16_t block_count;
};
const Slot kSlots[] = {
    {{41, "acceleration", 254}, 41, {{41, "acceleration", 254}, {42, "goal_position", 4095}}, 2},
    {{46, "goal_speed", 3000}, 44, {{44, "goal_time", 1000}, {46, "goal_speed", 3000}}, 3},
    {{48, "torque_limit", 1000}, 48, {{48, "torque_limit", 1000}}, 1},
};

struct ClientState {
  int unit = 1;
  const Slot* slot = nullptr;
  std::minstd_rand dice;
  std::map<std::uint16_t, std::uint16_t> acknowledged;  // address -> last value acknowledged
  std::map<std::uint16_t, bool> uncertain;              // a write to it failed after the last ack
  std::array<std::uint64_t, kRequestKinds> answered{};
  std::array<std::uint64_t, kRequestKinds> failed{};
  std::uint64_t writes_acknowledged = 0;
};

std::uint16_t next_value(ClientState& state, const OwnedField& field) {
  return static_cast<std::uint16_t>(state.dice() % (field.max + 1u));
}

Outcome one_request(modbus_t* context, ClientState& state) {
  const unsigned roll = state.dice() % 100;
  const std::size_t kind = roll < 35 ? 0 : roll < 60 ? 1 : roll < 80 ? 2 : 3;
  std::array<std::uint16_t, kFeedbackCount> registers{};
  int rc = -1;
  int expected = 0;
  std::vector<std::pair<std::uint16_t, std::uint16_t>> written;
  switch (kind) {
    case 0:
      expected = kFeedbackCount;
      rc = modbus_read_input_registers(context, kFeedbackAddress, kFeedbackCount, registers.data());
      break;
    case 1:
      expected = kFeedbackCount;
      rc = modbus_read_registers(context, kFeedbackAddress, kFeedbackCount, registers.data());
      break;
    case 2: {
      const OwnedField& field = state.slot->single;
      const std::uint16_t value = next_value(state, field);
      written.emplace_back(field.address, value);
      expected = 1;
      rc = modbus_write_register(context, field.address, value);
      break;
    }
    default: {
      const Slot& slot = *state.slot;
      std::vector<std::uint16_t> block(slot.block_count, 0);
      for (const OwnedField& field : slot.block) {
        const std::uint16_t value = next_value(state, field);
        block[field.address - slot.block_start] = value;
        written.emplace_back(field.address, value);
      }
      expected = slot.block_count;
      rc = modbus_write_registers(context, slot.block_start, slot.block_count, block.data());
      break;
    }
  }
  const Outcome outcome = outcome_of(rc, expected);
  if (outcome == Outcome::Ok) {
    ++state.answered[kind];
    for (const auto& [address, value] : written) {
      state.acknowledged[address] = value;
      state.uncertain[address] = false;
    }
    if (!written.empty()) ++state.writes_acknowledged;
  } else {
    ++state.failed[kind];
    // Not acknowledged: it may or may not have reached the servo; the next ack settles it.
    for (const auto& [address, value] : written) state.uncertain[address] = true;
  }
  return outcome;
}

struct RssSeries {
  std::vector<double> seconds;
  std::vector<double> kib;
  std::vector<std::uint64_t> fds;
};

// Least-squares slope of kib over seconds, in KiB per minute.
double slope_kib_per_min(const RssSeries& series, std::size_t from) {
  const std::size_t n = series.kib.size() - from;
  if (n < 2) return 0;
  double mean_t = 0, mean_k = 0;
  for (std::size_t i = from; i < series.kib.size(); ++i) {
    mean_t += series.seconds[i];
    mean_k += series.kib[i];
  }
  mean_t /= static_cast<double>(n);
  mean_k /= static_cast<double>(n);
  double covariance = 0, variance = 0;
  for (std::size_t i = from; i < series.kib.size(); ++i) {
    covariance += (series.seconds[i] - mean_t) * (series.kib[i] - mean_k);
    variance += (series.seconds[i] - mean_t) * (series.seconds[i] - mean_t);
  }
  return variance > 0 ? 60.0 * covariance / variance : 0;
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 60;
  if (const auto exit_status =
          parse_arguments(argc, argv,
                          "16 clients mixing FC03/FC04/FC06/FC16; gateway RSS every second; acknowledged writes read "
                          "back at the end",
                          {{"seconds", &seconds, "duration of the load"}})) {
    return *exit_status;
  }
  const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
  try {
    quiet_logs();
    sms::simulator::SimulatedBus bus(sts_bus(kServos));
    start_precise(bus);
    GatewaySetup setup;
    setup.device = bus.slave_path();
    setup.servos = kServos;
    BenchGateway gateway(setup);
    gateway.wait_ready(kServos);
    print_note(
        "sms-gateway, 6 simulated sts servos at 1 Mbaud (factory return delay 0, answered after 100 us: the sts "
        "floor), poll period 20 ms; 16 "
        "libmodbus clients; RSS = VmRSS of the gateway process, sampled every second");

    std::vector<ClientState> states(kClients);
    for (unsigned k = 0; k < kClients; ++k) {
      states[k].unit = static_cast<int>(1 + k % kServos);
      states[k].slot = &kSlots[k / kServos];
      states[k].dice.seed(1000 + k);
    }

    RssSeries rss;
    std::atomic<bool> sampling{true};
    const pid_t pid = gateway.pid();
    const auto idle_kib = rss_kib(pid);
    // Samples every second from one second into the load (all clients connected), to the end.
    std::thread sampler([&] {
      const auto start = Clock::now();
      auto next = start + 1s;
      while (sampling.load() && Clock::now() < next) std::this_thread::sleep_for(20ms);
      while (sampling.load()) {
        if (const auto kib = rss_kib(pid)) {
          rss.seconds.push_back(std::chrono::duration<double>(Clock::now() - start).count());
          rss.kib.push_back(static_cast<double>(*kib));
          rss.fds.push_back(open_fds(pid).value_or(0));
        }
        next += 1s;
        while (sampling.load() && Clock::now() < next) std::this_thread::sleep_for(20ms);
      }
    });

    // Each client's unit is set per request: run_clients connects them all to unit 1.
    ClientTotals totals =
        run_clients(gateway.port(), 1, kClients, duration, [&](modbus_t* context, unsigned client, std::uint64_t) {
          ClientState& state = states[client];
          modbus_set_slave(context, state.unit);
          return one_request(context, state);
        });
    sampling.store(false);
    sampler.join();

    // Read back every owned field through the gateway (FC03, live) and in the servo itself.
    ModbusClient checker(gateway.port(), 1);
    std::uint64_t checked = 0, mismatched = 0, unsettled = 0, writes_acknowledged = 0;
    for (unsigned k = 0; k < kClients; ++k) {
      ClientState& state = states[k];
      writes_acknowledged += state.writes_acknowledged;
      checker.set_unit(state.unit);
      for (const auto& [address, value] : state.acknowledged) {
        if (state.uncertain[address]) {
          ++unsettled;
          continue;
        }
        const std::uint16_t through_gateway =
            checker.read_holding(address, 1).or_throw("FC03 " + std::to_string(address)).at(0);
        const char* field_name = nullptr;
        for (const OwnedField& field : state.slot->block) {
          if (field.address == address) field_name = field.name;
        }
        if (state.slot->single.address == address) field_name = state.slot->single.name;
        const auto in_servo = bus.read_field(static_cast<std::uint8_t>(state.unit), field_name);
        ++checked;
        if (through_gateway != value || in_servo != value) {
          ++mismatched;
          print_note("MISMATCH unit " + std::to_string(state.unit) + " address " + std::to_string(address) +
                     ": acknowledged " + std::to_string(value) + ", gateway reads " + std::to_string(through_gateway) +
                     ", servo holds " + (in_servo ? std::to_string(*in_servo) : std::string("?")));
        }
      }
    }

    std::array<std::uint64_t, kRequestKinds> answered{}, failed{};
    for (const auto& state : states) {
      for (std::size_t kind = 0; kind < kRequestKinds; ++kind) {
        answered[kind] += state.answered[kind];
        failed[kind] += state.failed[kind];
      }
    }
    const std::string name = "soak.clients_16";
    print_figure(name + ".duration", totals.seconds, "s");
    for (std::size_t kind = 0; kind < kRequestKinds; ++kind) {
      print_figure(name + "." + kRequestNames[kind] + ".answered_per_s",
                   static_cast<double>(answered[kind]) / totals.seconds, "req/s");
      print_figure(name + "." + kRequestNames[kind] + ".failed", static_cast<double>(failed[kind]), "requests");
    }
    const LatencySummary latency = summarize(totals.ok_ns);
    print_figure(name + ".all.p50", latency.p50_us, "us");
    print_figure(name + ".all.p99", latency.p99_us, "us");
    if (totals.errors > 0) print_note("first failure: " + totals.first_error);
    if (!rss.kib.empty()) {
      if (idle_kib) print_figure(name + ".rss.before_load", static_cast<double>(*idle_kib), "KiB");
      print_figure(name + ".rss.first", rss.kib.front(), "KiB");
      print_figure(name + ".rss.last", rss.kib.back(), "KiB");
      print_figure(name + ".rss.max", *std::max_element(rss.kib.begin(), rss.kib.end()), "KiB");
      print_figure(name + ".rss.slope", slope_kib_per_min(rss, 0), "KiB/min");
      print_figure(name + ".rss.slope_second_half", slope_kib_per_min(rss, rss.kib.size() / 2), "KiB/min");
      print_figure(name + ".rss.samples", static_cast<double>(rss.kib.size()), "samples");
      print_figure(name + ".open_fds.first", static_cast<double>(rss.fds.front()), "fds");
      print_figure(name + ".open_fds.last", static_cast<double>(rss.fds.back()), "fds");
    }
    print_figure(name + ".writes_acknowledged", static_cast<double>(writes_acknowledged), "writes");
    print_figure(name + ".readback.checked", static_cast<double>(checked), "fields");
    print_figure(name + ".readback.unsettled", static_cast<double>(unsettled), "fields");
    print_figure(name + ".readback.mismatched", static_cast<double>(mismatched), "fields");
    if (const int status = gateway.stop(); status != 0) {
      std::cerr << "soak: sms-gateway exited with status " << status << "\n";
      return 1;
    }
    return mismatched == 0 ? 0 : 1;
  } catch (const std::exception& error) {
    std::cerr << "soak: " << error.what() << "\n";
    return 1;
  }
}
