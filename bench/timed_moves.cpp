// timed_moves: timed group moves (docs/PLC_GUIDE.md "Timed group moves") of 2, 6 and 20 sts
// axes on one 1 Mbit/s bus with wire timing: how far apart the axes arrive and how far each
// axis's move time is from the time asked, as the simulator's motor model records them.
//
//   timed_moves [--rounds 5] [--move-ms 1500]
//
// Each round homes every axis to 500 at its own speed (move time 0), waits until the group's
// distance to go reads 0 (the poll cache has seen them stand), then writes the goals
// 500 + d (d spread evenly from 100 to 3000 steps) and the move time in one FC16. Figures per
// axis count: the spread of the arrivals (last - first; the bound is 2 poll periods,
// 20 ms here), the largest |move time - T| / T over all axes and rounds, and the time from the
// FC16 being sent to the goals reaching the servos (cache or live reads, plan, one SYNC WRITE).
#include <algorithm>
#include <cmath>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr std::uint16_t kStart = 500;

struct Round {
  double spread_ms = 0;
  double worst_error_percent = 0;
  double start_latency_ms = 0;  // FC16 sent -> goals written on the servos
};

std::vector<sms::simulator::ServoSummary> wait_for_arrivals(sms::simulator::SimulatedBus& bus,
                                                            const std::vector<std::uint16_t>& goals,
                                                            Clock::time_point after) {
  const auto deadline = Clock::now() + 20s;
  while (Clock::now() < deadline) {
    auto servos = bus.servos();
    const bool all = std::all_of(servos.begin(), servos.end(), [&](const sms::simulator::ServoSummary& servo) {
      return servo.move_started && *servo.move_started > after && servo.arrived &&
             servo.present_position == goals[servo.config.id - 1];
    });
    if (all) return servos;
    std::this_thread::sleep_for(10ms);
  }
  throw std::runtime_error("the axes did not all reach their goals within 20 s");
}

// A servo that did not answer in time (0x0B: a loaded machine delays the simulator's thread) is
// no figure of the gateway's: the round is made again, at most kRetries times in a run.
constexpr unsigned kRetries = 3;
struct NotAnswered : std::runtime_error {
  using std::runtime_error::runtime_error;
};
void check(const sms::test::Answer<std::uint16_t>& answer, const std::string& what) {
  if (answer.ok()) return;
  if (answer.exception == 0x0B) throw NotAnswered(what + ": " + answer.error);
  throw std::runtime_error(what + " refused: " + answer.error);
}

Round run_round(sms::simulator::SimulatedBus& bus, ModbusClient& plc, unsigned axes, std::uint16_t move_ms) {
  const std::vector<std::uint16_t> home(axes, kStart);
  std::vector<std::uint16_t> request = home;
  request.push_back(0);
  auto before = Clock::now();
  check(plc.write_registers(0, request), "the homing write");
  wait_for_arrivals(bus, home, before);
  // As a PLC would: the next move once the group's distance to go (input register 2002, from the
  // poll cache the plan starts from) reads 0, not while the cache may still show the axes moving.
  const auto settled_by = Clock::now() + 10s;
  while (plc.read_input(2002, 1).or_throw("distance to go").at(0) != 0) {
    if (Clock::now() > settled_by) throw std::runtime_error("the poll cache never showed the axes home");
    std::this_thread::sleep_for(5ms);
  }

  std::vector<std::uint16_t> goals;
  for (unsigned axis = 0; axis < axes; ++axis) {
    const double distance = 100.0 + 2900.0 * axis / std::max(1U, axes - 1);
    goals.push_back(static_cast<std::uint16_t>(kStart + std::lround(distance)));
  }
  request = goals;
  request.push_back(move_ms);
  before = Clock::now();
  check(plc.write_registers(0, request), "the timed move");
  const auto servos = wait_for_arrivals(bus, goals, before);

  Round round;
  Clock::time_point first = Clock::time_point::max(), last = Clock::time_point::min();
  Clock::time_point earliest_start = Clock::time_point::max();
  for (const auto& servo : servos) {
    first = std::min(first, *servo.arrived);
    last = std::max(last, *servo.arrived);
    earliest_start = std::min(earliest_start, *servo.move_started);
    const double took_ms = std::chrono::duration<double, std::milli>(*servo.arrived - *servo.move_started).count();
    round.worst_error_percent = std::max(round.worst_error_percent, 100.0 * std::abs(took_ms - move_ms) / move_ms);
  }
  round.spread_ms = std::chrono::duration<double, std::milli>(last - first).count();
  round.start_latency_ms = std::chrono::duration<double, std::milli>(earliest_start - before).count();
  return round;
}

void measure(unsigned axes, unsigned rounds, std::uint16_t move_ms) {
  sms::simulator::SimulatedBus bus(sts_bus(axes));
  start_precise(bus);
  set_return_delay(bus, axes, kStsFastestReturnDelay);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = axes;
  setup.poll_period = 10ms;
  std::string members;
  for (unsigned id = 1; id <= axes; ++id) members += (id > 1 ? ", " : "") + std::to_string(id);
  setup.extra_yaml = "sync_groups:\n  - {name: arm, field: goal_position, members: [" + members +
                     "], holding_register_start: 0, move_time: true}\n";
  BenchGateway gateway(setup);
  gateway.wait_ready(axes);
  ModbusClient plc(gateway.port(), kGatewayUnit);

  double spread = 0, error = 0, latency = 0;
  unsigned retried = 0;
  for (unsigned r = 0; r < rounds; ++r) {
    Round round;
    try {
      round = run_round(bus, plc, axes, move_ms);
    } catch (const NotAnswered& late) {
      if (++retried > kRetries) throw;
      std::cerr << "timed_moves: " << late.what() << "; the round is made again\n";
      --r;
      continue;
    }
    spread = std::max(spread, round.spread_ms);
    error = std::max(error, round.worst_error_percent);
    latency = std::max(latency, round.start_latency_ms);
  }
  const std::string name = "timed_moves." + std::to_string(axes) + "_axes";
  print_figure(name + ".arrival_spread.max", spread, "ms");
  print_figure(name + ".move_time_error.max", error, "%");
  print_figure(name + ".request_to_goals.max", latency, "ms");
  print_figure(name + ".rounds_made_again", retried, "rounds");
  if (gateway.stop() != 0) throw std::runtime_error("the gateway did not stop cleanly");
}

}  // namespace

int main(int argc, char** argv) {
  double rounds = 5;
  double move_ms = 1500;
  if (const auto exit_status = parse_arguments(
          argc, argv, "timed group moves of 2, 6 and 20 sts axes: arrival spread and move time error",
          {{"rounds", &rounds, "timed moves per axis count"}, {"move-ms", &move_ms, "the move time written, ms"}})) {
    return *exit_status;
  }
  quiet_logs();
  try {
    print_note("poll period 10 ms, 1 Mbit/s, wire timing on; distances 100..3000 steps; move time " +
               std::to_string(static_cast<int>(move_ms)) + " ms");
    for (const unsigned axes : {2U, 6U, 20U}) {
      measure(axes, static_cast<unsigned>(rounds), static_cast<std::uint16_t>(move_ms));
    }
  } catch (const std::exception& error) {
    std::cerr << "timed_moves: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
