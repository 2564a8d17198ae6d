// trip_latency: how long a watchdog trip takes to stop the servos (issue 10, README "Safety"):
// from the last feed — the last Modbus write a PLC sent — to the stop frame on the wire, for
// buses of 6 and 60 simulated sts servos at 1 000 000 baud with wire timing on.
//
//   trip_latency [--rounds 20] [--timeout-ms 100] [--servos N]
//
// Each round a client puts every servo into constant-speed mode (operating mode 1, goal speed
// 1000 steps/s), then goes silent; the time it sent its last write is the last feed. The bench
// watches the simulated servos in its own process (no bus traffic): the stop has landed when the
// last servo's goal speed reads 0, which only the safe stop's SYNC WRITE writes. That instant,
// minus the last feed, is the trip latency; minus the watchdog timeout, what the stop costs
// beyond it: the watchdog thread's wake-up, one READ per servo (mode, torque, goal block,
// present position: the hold needs them), the SYNC WRITE frame. Between rounds the client
// re-arms the watchdog (gateway unit coil 2 := 0). The gateway's own figure (unit 255 input
// registers 116-117, last feed -> its stop frames completed) is printed beside it.
#include <modbus/modbus.h>

#include <algorithm>
#include <cstdlib>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServoCounts[] = {6, 60};
constexpr int kModeAddress = 33;        // sts operating_mode
constexpr int kGoalSpeedAddress = 46;   // sts goal_speed
constexpr std::uint16_t kGoalSpeed = 1000;
constexpr int kWatchdogCoil = 2;
constexpr int kLastStopLatency = 116;   // bus 0: 100 + 16, 32-bit µs
constexpr auto kWatchEvery = 20us;

void write_or_throw(modbus_t* context, int unit, int address, std::uint16_t value) {
  modbus_set_slave(context, unit);
  if (modbus_write_register(context, address, value) != 1) {
    throw std::runtime_error("unit " + std::to_string(unit) + ": write " + std::to_string(address) + " failed: " +
                             modbus_error_text());
  }
}

bool all_stopped(sms::simulator::SimulatedBus& bus, unsigned servos) {
  for (unsigned id = 1; id <= servos; ++id) {
    if (bus.read_field(static_cast<std::uint8_t>(id), "goal_speed").value_or(1) != 0) return false;
  }
  return true;
}

void measure(unsigned servos, unsigned rounds, std::chrono::milliseconds timeout) {
  sms::simulator::SimulatedBus bus(sts_bus(servos));
  start_precise(bus);
  set_return_delay(bus, servos, 0);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = servos;
  setup.watchdog = timeout;
  GatewayProcess gateway(setup);
  gateway.wait_ready(servos);
  ModbusClient client(gateway.port(), 1);
  for (unsigned id = 1; id <= servos; ++id) write_or_throw(client.get(), static_cast<int>(id), kModeAddress, 1);

  std::vector<std::uint32_t> total_ns;
  std::vector<std::uint32_t> beyond_ns;
  std::vector<std::uint32_t> reported_ns;
  unsigned missed = 0;
  for (unsigned round = 0; round < rounds; ++round) {
    modbus_set_slave(client.get(), kGatewayUnit);
    if (modbus_write_bit(client.get(), kWatchdogCoil, 0) != 1) throw std::runtime_error("re-arm: " + modbus_error_text());
    Clock::time_point last_feed;
    for (unsigned id = 1; id <= servos; ++id) {
      last_feed = Clock::now();
      write_or_throw(client.get(), static_cast<int>(id), kGoalSpeedAddress, kGoalSpeed);
    }
    // Every servo turns before the watch starts: the stop is the only way back to speed 0.
    const auto give_up = last_feed + timeout * 20 + 2s;
    Clock::time_point stopped{};
    while (Clock::now() < give_up) {
      if (all_stopped(bus, servos)) {
        stopped = Clock::now();
        break;
      }
      std::this_thread::sleep_for(kWatchEvery);
    }
    if (stopped == Clock::time_point{}) {
      ++missed;
      continue;
    }
    total_ns.push_back(to_ns(stopped - last_feed));
    beyond_ns.push_back(to_ns(std::max(stopped - last_feed - timeout, Clock::duration::zero())));
    client.set_unit(kGatewayUnit);
    const auto latency = client.input_registers(kLastStopLatency, 2);
    reported_ns.push_back(u32(latency[0], latency[1]) * 1000u);
  }
  gateway.stop();

  const std::string name = "trip_latency.servos_" + std::to_string(servos);
  const auto total = summarize(total_ns);
  const auto beyond = summarize(beyond_ns);
  const auto reported = summarize(reported_ns);
  print_figure(name + ".timeout", static_cast<double>(timeout.count()), "ms");
  print_figure(name + ".rounds", static_cast<double>(total.count), "");
  print_figure(name + ".missed", missed, "");
  print_figure(name + ".last_feed_to_stop_frame.p50", total.p50_us / 1000.0, "ms");
  print_figure(name + ".last_feed_to_stop_frame.p99", total.p99_us / 1000.0, "ms");
  print_figure(name + ".last_feed_to_stop_frame.max", total.max_us / 1000.0, "ms");
  print_figure(name + ".beyond_timeout.p50", beyond.p50_us / 1000.0, "ms");
  print_figure(name + ".beyond_timeout.p99", beyond.p99_us / 1000.0, "ms");
  print_figure(name + ".gateway_reported.p50", reported.p50_us / 1000.0, "ms");
  print_figure(name + ".gateway_reported.p99", reported.p99_us / 1000.0, "ms");
  // What the stop has to do on the wire: one READ of 25 bytes per servo, then one SYNC WRITE of
  // the 6-byte goal block to every servo (SPEC §5 wire time, return delay 0).
  const double reads_us = servos * wire_us(8 + 6 + 25);
  const double frame_us = wire_us(8 + servos * 7);
  print_figure(name + ".wire_model.reads_then_frame", (reads_us + frame_us) / 1000.0, "ms");
}

}  // namespace

int main(int argc, char** argv) {
  double rounds = 20;
  double timeout_ms = 100;
  double only_servos = 0;
  if (!parse_arguments(argc, argv,
                       "watchdog trip latency (last feed -> stop frame on the wire) for 6 and 60 servos at 1 Mbaud",
                       {{"rounds", &rounds, "trips per bus size"},
                        {"timeout-ms", &timeout_ms, "the watchdog timeout"},
                        {"servos", &only_servos, "only this bus size (6 or 60; 0: both)"}})) {
    return 2;
  }
  try {
    quiet_logs();
    double load[3] = {0, 0, 0};
    if (getloadavg(load, 3) == 3) print_figure("load_average_1min", load[0], "");
    print_note("a client makes every servo turn, then goes silent; stop = last servo's goal speed reads 0 in the "
               "simulator (polled every 20 us in-process); gateway_reported = unit 255 input registers 116-117");
    for (const unsigned servos : kServoCounts) {
      if (only_servos > 0 && only_servos != servos) continue;
      measure(servos, static_cast<unsigned>(rounds), std::chrono::milliseconds(static_cast<long>(timeout_ms)));
    }
  } catch (const std::exception& error) {
    std::cerr << "trip_latency: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
