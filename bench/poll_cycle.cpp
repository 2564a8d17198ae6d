// poll_cycle: the gateway's poll cycle time next to the wire-time limit of the frames it sends
// (docs/PROTOCOL.md §5), for 6, 20 and 60 simulated sts servos at 1 000 000 baud with wire timing on; then
// what a silent servo costs the others (bench (b)); then a modbus-rtu bus of 6 SMSMB
// servos at 115 200 bit/s with each frame_gap setting (bench (f)).
//
//   poll_cycle [--seconds 2] [--silent-seconds 5] [--servos N] [--return-delay-us D] [--rtu-seconds 2]
//
// --servos and --return-delay-us pick one bus size / one return delay (0 = all; the return delay
// applies to the modbus-rtu part too); --seconds 0, --silent-seconds 0 and --rtu-seconds 0 skip
// the feetech, the silent-servo and the modbus-rtu part.
//
// The gateway (sms-gateway, a child process) polls back to back (poll_period_ms 0) so every
// cycle is pure bus work. The cycle time is what the gateway itself reports: gateway unit 255,
// input register 102 "last poll cycle us", sampled every 10 ms. The limit is one SYNC READ of
// the 15-byte feedback block from N servos: (8 + N) request bytes + N x (6 + 15) reply bytes
// at 10 bits a character, plus N return delays (sts address 7, x 2 us). Efficiency = limit /
// measured median cycle. Measured with return delay 0 (docs/PROTOCOL.md §5's example) and with the sts
// factory default 250 (500 us).
// The register says how long one cycle took, from its start to its last answer. The bus's
// real poll rate also pays for the time between cycles and for the occasional long cycle (a
// busy machine): cycle_mean_from_frame_rate is 1 / cycles per second, counted from the frames
// answered in the window, and efficiency_throughput = limit / that.
// The limit is the wire alone: it leaves out the time the pty and the simulator take to pass
// the request over and the last answer back (a real adapter has its own latency instead).
#include <algorithm>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServoCounts[] = {6, 20, 60};
constexpr std::uint8_t kReturnDelays[] = {kStsFastestReturnDelay, 250};  // sts address 7 units (x 2 us)
constexpr unsigned kSilentBusServos = 6;
constexpr std::uint8_t kSilentServo = 3;
constexpr auto kSampleEvery = 10ms;
constexpr auto kProbePeriod = 1000ms;
constexpr auto kResponseTimeout = 20ms;  // the configuration default the gateway runs with

double sync_read_limit_us(unsigned servos, std::uint8_t return_delay) {
  const std::size_t request = 8 + servos;
  const std::size_t replies = servos * (6 + kFeedbackCount);
  return wire_us(request + replies) + servos * return_delay * kReturnDelayUsPerUnit;
}

struct Window {
  std::vector<std::uint32_t> cycle_us;  // sampled "last poll cycle us"
  double seconds = 0;
  BusFacts first;
  BusFacts last;
  ServoFacts watched_first;  // servo unit 1 (always online)
  ServoFacts watched_last;
  ServoFacts silent_first;  // the servo taken offline
  ServoFacts silent_last;
};

Window sample(ModbusClient& client, std::chrono::milliseconds duration) {
  Window window;
  window.watched_first = read_servo_facts(client, 1);
  window.silent_first = read_servo_facts(client, kSilentServo);
  window.first = read_bus_facts(client);
  const auto start = Clock::now();
  const auto end = start + duration;
  auto next = start;
  while (Clock::now() < end) {
    next += kSampleEvery;
    window.cycle_us.push_back(read_bus_facts(client).last_poll_cycle_us);
    std::this_thread::sleep_until(next);
  }
  window.last = read_bus_facts(client);
  window.watched_last = read_servo_facts(client, 1);
  window.silent_last = read_servo_facts(client, kSilentServo);
  window.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return window;
}

double mean(const std::vector<std::uint32_t>& values) {
  if (values.empty()) return 0;
  double sum = 0;
  for (const auto value : values) sum += value;
  return sum / static_cast<double>(values.size());
}

double median(std::vector<std::uint32_t> values) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

double per_second(std::uint32_t before, std::uint32_t after, double seconds) {
  return static_cast<double>(after - before) / seconds;
}

void measure_cycle(unsigned servos, std::uint8_t return_delay, std::chrono::milliseconds duration) {
  sms::simulator::SimulatedBus bus(sts_bus(servos));
  start_precise(bus);
  set_return_delay(bus, servos, return_delay);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = servos;
  setup.poll_period = 0ms;
  BenchGateway gateway(setup);
  gateway.wait_ready(servos);
  ModbusClient client(gateway.port(), kGatewayUnit);
  std::this_thread::sleep_for(200ms);  // past discovery's last identity reads

  const Window window = sample(client, duration);
  const double limit = sync_read_limit_us(servos, return_delay);
  const double measured = median(window.cycle_us);
  // Every servo answers once per cycle in one SYNC READ: frames / servos = cycles.
  const double cycles_per_s = per_second(window.first.frames_ok, window.last.frames_ok, window.seconds) / servos;
  const std::string name = "poll_cycle.servos_" + std::to_string(servos) + ".return_delay_us_" +
                           std::to_string(static_cast<int>(return_delay * kReturnDelayUsPerUnit));
  print_figure(name + ".wire_limit", limit, "us");
  const double from_rate = cycles_per_s > 0 ? 1e6 / cycles_per_s : 0;
  print_figure(name + ".cycle_median", measured, "us");
  print_figure(name + ".cycle_mean_sampled", mean(window.cycle_us), "us");
  print_figure(name + ".cycle_mean_from_frame_rate", from_rate, "us");
  print_figure(name + ".efficiency", measured > 0 ? 100.0 * limit / measured : 0, "%");
  print_figure(name + ".efficiency_throughput", from_rate > 0 ? 100.0 * limit / from_rate : 0, "%");
  print_figure(name + ".timeouts", window.last.timeouts - window.first.timeouts, "frames");
  gateway.stop();
}

// modbus-rtu: one FC03 of the 8-register feedback block per servo and cycle, each
// followed by the configured inter-frame gap. Limit = N x (8 request + 21 reply bytes on the
// wire + the servo's return delay + the gap): what the gap setting allows, not only the wire.
struct RtuGap {
  std::string setting;  // config frame_gap
  double gap_us;        // what it is at kRtuBaud
};
constexpr std::uint32_t kRtuBaud = 115'200;
constexpr unsigned kRtuServos = 6;
constexpr std::uint16_t kSmsmbReturnDelayRegister = 0x0C;
constexpr std::uint16_t kRtuReturnDelaysUs[] = {0, 500};  // SMSMB register 0x0C (1 us a unit), default 500

void measure_rtu_cycle(const RtuGap& gap, std::uint16_t return_delay_us, std::chrono::milliseconds duration) {
  sms::simulator::SimulatedBus bus(smsmb_bus(kRtuServos, kRtuBaud));
  start_precise(bus);
  // SMSMB register 0x0C: the return delay in us, high byte first (Modbus).
  const std::uint8_t delay[] = {static_cast<std::uint8_t>(return_delay_us >> 8),
                                static_cast<std::uint8_t>(return_delay_us & 0xFF)};
  for (unsigned id = 1; id <= kRtuServos; ++id)
    bus.write_memory(static_cast<std::uint8_t>(id), kSmsmbReturnDelayRegister, delay);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = kRtuServos;
  setup.poll_period = 0ms;
  setup.modbus_rtu_baud = kRtuBaud;
  setup.frame_gap = gap.setting;
  BenchGateway gateway(setup);
  gateway.wait_ready(kRtuServos);
  ModbusClient client(gateway.port(), kGatewayUnit);
  std::this_thread::sleep_for(200ms);
  const auto merged_before = bus.stats().merged_requests;
  const Window window = sample(client, duration);
  const double per_servo_wire = wire_us(8 + 21, kRtuBaud);
  const double limit = kRtuServos * (per_servo_wire + return_delay_us + gap.gap_us);
  const double measured = median(window.cycle_us);
  const double cycles_per_s = per_second(window.first.frames_ok, window.last.frames_ok, window.seconds) / kRtuServos;
  const double from_rate = cycles_per_s > 0 ? 1e6 / cycles_per_s : 0;
  const std::string name = "poll_cycle.modbus_rtu.servos_6.baud_115200.return_delay_us_" +
                           std::to_string(return_delay_us) + ".frame_gap_" + gap.setting;
  print_figure(name + ".wire_only", kRtuServos * per_servo_wire, "us");
  print_figure(name + ".limit_with_gap", limit, "us");
  print_figure(name + ".cycle_median", measured, "us");
  print_figure(name + ".cycle_mean_from_frame_rate", from_rate, "us");
  print_figure(name + ".efficiency", measured > 0 ? 100.0 * limit / measured : 0, "%");
  print_figure(name + ".efficiency_throughput", from_rate > 0 ? 100.0 * limit / from_rate : 0, "%");
  print_figure(name + ".wire_share", measured > 0 ? 100.0 * kRtuServos * per_servo_wire / measured : 0, "%");
  print_figure(name + ".timeouts", window.last.timeouts - window.first.timeouts, "frames");
  print_figure(name + ".merged_requests", static_cast<double>(bus.stats().merged_requests - merged_before), "");
  gateway.stop();
}

void measure_silent_servo(std::chrono::milliseconds duration) {
  sms::simulator::SimulatedBus bus(sts_bus(kSilentBusServos));
  start_precise(bus);
  set_return_delay(bus, kSilentBusServos, kStsFastestReturnDelay);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = kSilentBusServos;
  setup.poll_period = 0ms;
  setup.probe_period = kProbePeriod;
  BenchGateway gateway(setup);
  gateway.wait_ready(kSilentBusServos);
  ModbusClient client(gateway.port(), kGatewayUnit);
  std::this_thread::sleep_for(200ms);

  const Window all_online = sample(client, duration);

  bus.set_offline(kSilentServo, true);
  const auto went_silent = Clock::now();
  while (read_servo_facts(client, kSilentServo).online) {
    if (Clock::now() - went_silent > 5s) throw std::runtime_error("the silent servo was never marked offline");
    std::this_thread::sleep_for(1ms);
  }
  const double detection_ms = std::chrono::duration<double, std::milli>(Clock::now() - went_silent).count();
  std::this_thread::sleep_for(100ms);
  const Window one_offline = sample(client, duration);

  bus.set_offline(kSilentServo, false);
  const auto came_back = Clock::now();
  while (!read_servo_facts(client, kSilentServo).online) {
    // Its probe brings it back within a probe period or two on an idle machine (back_ms below
    // says how long it took); the bound is only that it comes back: on a loaded one (the test
    // command's run of this benchmark) its probes' answers can be late too, and a servo that
    // answers late stays offline until one comes in time (docs/DECISIONS.md).
    if (Clock::now() - came_back > 10s) throw std::runtime_error("the servo never came back online");
    std::this_thread::sleep_for(1ms);
  }
  const double back_ms = std::chrono::duration<double, std::milli>(Clock::now() - came_back).count();

  const unsigned online = kSilentBusServos - 1;
  const double limit = sync_read_limit_us(online, kStsFastestReturnDelay);
  const double measured = median(one_offline.cycle_us);
  const double probes_per_s =
      per_second(one_offline.silent_first.timeouts, one_offline.silent_last.timeouts, one_offline.seconds);
  // One probe = one READ of the feedback block, one attempt: its wire time + the response timeout.
  const double probe_cost_ms =
      (wire_us(8) + wire_us(6 + kFeedbackCount)) / 1000.0 + static_cast<double>(kResponseTimeout.count());
  const double rate_all =
      per_second(all_online.watched_first.replies_ok, all_online.watched_last.replies_ok, all_online.seconds);
  const double rate_one_off =
      per_second(one_offline.watched_first.replies_ok, one_offline.watched_last.replies_ok, one_offline.seconds);
  const std::string name = "silent_servo.servos_6.return_delay_us_100";
  print_figure(name + ".detected_offline_after", detection_ms, "ms");
  print_figure(name + ".others.wire_limit", limit, "us");
  print_figure(name + ".others.cycle_median", measured, "us");
  print_figure(name + ".others.efficiency", measured > 0 ? 100.0 * limit / measured : 0, "%");
  print_figure(name + ".cycle_max_sampled", *std::max_element(one_offline.cycle_us.begin(), one_offline.cycle_us.end()),
               "us");
  print_figure(name + ".probe_period", static_cast<double>(kProbePeriod.count()), "ms");
  print_figure(name + ".probes_per_s", probes_per_s, "1/s");
  print_figure(name + ".bus_timeouts_per_s",
               per_second(one_offline.first.timeouts, one_offline.last.timeouts, one_offline.seconds), "1/s");
  print_figure(name + ".bus_time_lost", probes_per_s * probe_cost_ms, "ms/s");
  print_figure(name + ".servo1_poll_rate.all_online", rate_all, "Hz");
  print_figure(name + ".servo1_poll_rate.one_offline", rate_one_off, "Hz");
  print_figure(name + ".servo1_poll_rate.loss", rate_all > 0 ? 100.0 * (rate_all - rate_one_off) / rate_all : 0, "%");
  print_figure(name + ".back_online_after", back_ms, "ms");
  gateway.stop();
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 2;
  double silent_seconds = 5;
  double only_servos = 0;
  double only_return_delay_us = -1;
  double rtu_seconds = 2;
  if (const auto exit_status = parse_arguments(
          argc, argv,
          "poll cycle time vs the SYNC READ wire-time limit for 6, 20, 60 servos at 1 Mbaud; the cost "
          "of one silent servo",
          {{"seconds", &seconds, "sampling time per bus size"},
           {"silent-seconds", &silent_seconds, "sampling time with and without the silent servo (0: skip)"},
           {"servos", &only_servos, "only this bus size (6, 20 or 60; 0: all)"},
           {"return-delay-us", &only_return_delay_us, "only this return delay (100 or 500; -1: both)"},
           {"rtu-seconds", &rtu_seconds, "sampling time per modbus-rtu frame gap setting (0: skip)"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    print_note(
        "sms-gateway polling back to back (poll_period_ms 0); cycle = gateway unit 255 input register 102, "
        "sampled every 10 ms; limit = SYNC READ of 15 bytes, docs/PROTOCOL.md §5");
    for (const std::uint8_t return_delay : kReturnDelays) {
      if (seconds <= 0) break;
      if (only_return_delay_us >= 0 && only_return_delay_us != return_delay * kReturnDelayUsPerUnit) continue;
      for (const unsigned servos : kServoCounts) {
        if (only_servos > 0 && only_servos != servos) continue;
        measure_cycle(servos, return_delay, std::chrono::milliseconds(static_cast<long>(seconds * 1000)));
      }
    }
    if (rtu_seconds > 0) {
      print_note(
          "modbus-rtu: 6 SMSMB servos at 115200 bit/s, FC03 of 8 registers each, return delay 0 and 500 us "
          "(the SMSMB default), with each frame_gap setting; limit = frames on the wire + return delay + one "
          "gap per transaction");
      const double characters_us = 3.5 * 10 * 1e6 / kRtuBaud;
      for (const std::uint16_t return_delay_us : kRtuReturnDelaysUs) {
        if (only_return_delay_us >= 0 && only_return_delay_us != return_delay_us) continue;
        for (const RtuGap& gap : {RtuGap{"spec", 1750}, RtuGap{"3.5chars", characters_us}, RtuGap{"500us", 500}}) {
          measure_rtu_cycle(gap, return_delay_us, std::chrono::milliseconds(static_cast<long>(rtu_seconds * 1000)));
        }
      }
    }
    if (silent_seconds > 0) {
      measure_silent_servo(std::chrono::milliseconds(static_cast<long>(silent_seconds * 1000)));
    }
  } catch (const std::exception& error) {
    std::cerr << "poll_cycle: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
