// stop_distance: how far an axis runs on after a safe stop (docs/SAFETY.md "Stop distance"), on
// every table: a move at the table's top speed on a ramp the PLC left (plain), and a timed move
// on the plan's ramp (timed), each stopped by the e-stop mid-way. The simulator's motor model is
// the witness: where the motor was when the stop's frame arrived, where it stood, whether it
// turned back, and how long it took to stand.
//
//   stop_distance [--rounds 10]
//
// Figures per table and kind: the largest run-on (steps, d55d degrees at resolution 10), the
// longest time from the stop's frame to standing still, the rounds in which an axis turned back,
// and the e-stop request to the stop's frame at the servo.
#include <algorithm>
#include <cmath>
#include <cstdlib>
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

struct Write {
  int address;
  std::uint16_t value;
};

struct Axis {
  std::string name;
  TableId table;
  BusProtocol protocol;
  std::string bus_protocol;  // config
  std::uint32_t baud;
  std::vector<Write> setup;  // torque on, top speed, the move's ramp
  int goal_address;
  int start;
  int distance;
  std::uint16_t move_time_ms;
};

// Top speed with a brisk ramp that reaches it a third of the way; the timed move is the plan's.
const std::vector<Axis> kAxes{
    {"sts",
     TableId::Sts,
     BusProtocol::Feetech,
     "feetech",
     1000000,
     {{40, 1}, {41, 50}, {46, 100}},
     42,
     300,
     3500,
     1500},
    {"sms1",
     TableId::Sms1,
     BusProtocol::Feetech,
     "feetech",
     1000000,
     {{40, 1}, {41, 50}, {46, 4500}},
     42,
     300,
     3500,
     1500},
    {"scs", TableId::Scs, BusProtocol::Feetech, "feetech", 1000000, {{40, 1}, {46, 1500}}, 42, 100, 800, 1500},
    {"d55d",
     TableId::D55d,
     BusProtocol::D55d,
     "d55d",
     115200,
     {{8, 3600}, {32, 360}, {34, 50}, {35, 50}},
     30,
     0,
     300,
     3000},
    {"smsmb",
     TableId::Smsmb,
     BusProtocol::ModbusRtu,
     "modbus-rtu",
     115200,
     {{0x81, 1}, {0x82, 50}, {0x83, 100}},
     0x80,
     300,
     3500,
     1500},
};

struct Stop {
  double run_on = 0;  // position units past where the stop's frame found the motor
  double stand_ms = 0;
  bool reversed = false;
  double turned_back = 0;  // how far it came back from the farthest point it reached
  double request_to_frame_ms = 0;
};

// The e-stop's frames not acknowledged in time (0x04: a loaded machine delays the simulator past
// the response timeout; the servo is then owed its stop), a setup write refused while the servo
// was offline for the same reason, or a d55d motor its own heartbeat stopped: no run-on to
// measure, the round is made again once the servo is polled again, at most kRetries times a table.
constexpr unsigned kRetries = 3;
struct NotAcknowledged : std::runtime_error {
  using std::runtime_error::runtime_error;
};

sms::simulator::ServoSummary servo_of(sms::simulator::SimulatedBus& bus) { return bus.servos().at(0); }

// Waits for the motor to stand at the goal of a write made after `after`.
sms::simulator::ServoSummary wait_standing(sms::simulator::SimulatedBus& bus, Clock::time_point after, int goal = -1) {
  const auto deadline = Clock::now() + 20s;
  while (Clock::now() < deadline) {
    const auto servo = servo_of(bus);
    if (servo.move_started && *servo.move_started > after && servo.arrived &&
        servo.present_position == servo.goal_position && (goal < 0 || servo.goal_position == goal)) {
      return servo;
    }
    std::this_thread::sleep_for(2ms);
  }
  throw std::runtime_error("the axis did not come to stand within 20 s");
}

Stop run_round(const Axis& axis, sms::simulator::SimulatedBus& bus, ModbusClient& plc, ModbusClient& panel,
               bool timed) {
  // Home at the start, as fast as it goes, the e-stop reset first.
  if (!panel.write_coil(1, false).ok()) throw std::runtime_error("e-stop reset refused");
  // A write refused while the servo is offline (a loaded machine held the simulator past the
  // response timeout) makes the round again once the servo is back.
  const auto acknowledged = [](const auto& answer, const char* what) {
    if (!answer.ok()) throw NotAcknowledged(std::string(what) + " was answered with " + answer.error);
  };
  for (const Write& write : axis.setup) acknowledged(plc.write_register(write.address, write.value), "a setup write");
  auto before = Clock::now();
  acknowledged(plc.write_register(axis.goal_address, static_cast<std::uint16_t>(axis.start)), "the homing write");
  wait_standing(bus, before, axis.start);
  for (const Write& write : axis.setup) acknowledged(plc.write_register(write.address, write.value), "a setup write");
  const auto goal = static_cast<std::uint16_t>(axis.start + axis.distance);
  before = Clock::now();
  if (timed) {
    acknowledged(panel.write_registers(0, {goal, axis.move_time_ms}), "the timed move");
  } else {
    acknowledged(plc.write_register(axis.goal_address, goal), "the move");
  }
  // Stop two thirds of the way: at top speed on the plain move, at the plan's cruise on the timed.
  const auto deadline = Clock::now() + 20s;
  const std::uint64_t heartbeat_stops = servo_of(bus).heartbeat_stops;
  while (servo_of(bus).present_position < axis.start + 2 * axis.distance / 3) {
    // A d55d motor left 500 ms without an instruction (a loaded machine held the gateway's bus
    // thread) stops itself: no stop to measure, the round is made again.
    if (servo_of(bus).heartbeat_stops != heartbeat_stops) {
      throw NotAcknowledged("the motor's own heartbeat stopped it before the e-stop (the gateway was held 500 ms)");
    }
    if (Clock::now() > deadline) throw std::runtime_error("the axis never got two thirds of the way");
    std::this_thread::sleep_for(1ms);
  }
  const auto request = Clock::now();
  if (const auto answer = panel.write_coil(1, true); !answer.ok()) {
    throw NotAcknowledged("the e-stop was answered with " + answer.error);
  }
  const auto stopped = wait_standing(bus, request);
  Stop stop;
  stop.run_on = std::abs(stopped.present_position - stopped.position_at_goal);
  stop.stand_ms = std::chrono::duration<double, std::milli>(*stopped.arrived - *stopped.move_started).count();
  stop.reversed = stopped.reversed;
  stop.turned_back = stopped.turned_back;
  stop.request_to_frame_ms = std::chrono::duration<double, std::milli>(*stopped.move_started - request).count();
  return stop;
}

void measure(const Axis& axis, unsigned rounds) {
  sms::simulator::BusOptions options;
  options.servos.push_back(sms::simulator::ServoConfig{1, axis.table, axis.protocol, axis.baud});
  options.timing = true;
  options.seed = 1;
  sms::simulator::SimulatedBus bus(options);
  start_precise(bus);
  sms::test::TempDir dir;
  // Response timeout 500 ms: a loaded machine (the test command's run of this benchmark) holds the
  // simulator past 100 ms; the run-on measured does not depend on it.
  const std::string yaml = "buses:\n  - {name: line, device: \"" + bus.slave_path() +
                           "\", protocol: " + axis.bus_protocol + ", baud: " + std::to_string(axis.baud) +
                           ", poll_period_ms: 10, response_timeout_ms: 500, retries: 1}\nservos:\n"
                           "  - {unit: 1, bus: line, id: 1, table: " +
                           axis.name +
                           "}\nsync_groups:\n  - {name: arm, field: goal_position, members: [1], "
                           "holding_register_start: 0, move_time: true}\n";
  GatewayProcess gateway = GatewayProcess::with_config(dir, yaml, 1, {}, gateway_program());
  sms::test::wait_until_polled(gateway.port(), 1);
  ModbusClient plc(gateway.port(), 1);
  ModbusClient panel(gateway.port(), kGatewayUnit);
  for (const bool timed : {false, true}) {
    double run_on = 0, stand = 0, latency = 0, back = 0;
    unsigned reversals = 0;
    unsigned retried = 0;
    for (unsigned r = 0; r < rounds; ++r) {
      Stop stop;
      try {
        stop = run_round(axis, bus, plc, panel, timed);
      } catch (const NotAcknowledged& late) {
        if (++retried > kRetries) throw;
        std::cerr << "stop_distance: " << axis.name << ": " << late.what() << "; the round is made again\n";
        sms::test::wait_until_polled(gateway.port(), 1);
        --r;
        continue;
      } catch (const std::exception& error) {
        throw std::runtime_error(axis.name + ": " + error.what() + "; the gateway said:\n" +
                                 gateway.process().output());
      }
      run_on = std::max(run_on, stop.run_on);
      stand = std::max(stand, stop.stand_ms);
      latency = std::max(latency, stop.request_to_frame_ms);
      reversals += stop.reversed ? 1 : 0;
      back = std::max(back, stop.turned_back);
    }
    const std::string name = "stop_distance." + axis.name + (timed ? ".timed_move" : ".top_speed");
    print_figure(name + ".run_on.max", run_on, axis.table == TableId::D55d ? "deg" : "steps");
    print_figure(name + ".frame_to_standing.max", stand, "ms");
    print_figure(name + ".turned_back", reversals, "rounds");
    print_figure(name + ".turned_back.max", back, axis.table == TableId::D55d ? "deg" : "steps");
    print_figure(name + ".request_to_frame.max", latency, "ms");
    print_figure(name + ".rounds_made_again", retried, "rounds");
  }
  if (gateway.stop() != 0) throw std::runtime_error("the gateway did not stop cleanly");
}

}  // namespace

int main(int argc, char** argv) {
  double rounds = 10;
  if (const auto exit_status =
          parse_arguments(argc, argv,
                          "run-on of a safe stop from top speed and from a timed move, on every table (the simulator's "
                          "motor model)",
                          {{"rounds", &rounds, "stops per table and kind"}})) {
    return *exit_status;
  }
  quiet_logs();
  try {
    print_note("e-stop two thirds into a move; wire timing on; d55d at resolution 10 (1 deg a unit)");
    for (const Axis& axis : kAxes) measure(axis, static_cast<unsigned>(rounds));
  } catch (const std::exception& error) {
    std::cerr << "stop_distance: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
