// write_latency: live FC06 writes and FC03 reads against one servo, through the gateway, next
// to the wire time the frames need (docs/PROTOCOL.md §5) and to the same bus transaction done directly on a
// pty by this program — the gateway's own overhead per transaction (bench (c)).
//
//   write_latency [--seconds 3]
//
// Model: (request + reply bytes) x 10 / baud + return delay (100 us here, the fastest an sts
// servo answers). FC06 to goal_position (42) is one WRITE of 2 bytes: 9 request + 6 reply bytes
// = 150 us + 100 us. FC03 of 56+15 is one READ: 8 + 21 bytes = 290 us + 100 us.
// "direct" is the same frame written by this program to a second simulated bus through the
// gateway's own SerialPort class (flush, write, wait for the whole reply): the pty and the
// simulator's cost, which a real adapter replaces by its own latency.
// The gateway runs twice: with a quiet bus (poll period 1 h: no poll traffic competes) and with
// its default 20 ms poll period (a client transaction may wait for a poll transaction).
#include <array>
#include <iostream>
#include <string>
#include <thread>

#include <modbus/modbus.h>

#include "bench/bench_support.h"
#include "gateway/bus/serial_port.h"
#include "protocol/instructions.h"
#include "protocol/packet.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr std::uint16_t kGoalPositionAddress = 42;
constexpr std::size_t kAckBytes = 6;
constexpr std::size_t kWriteRequestBytes = 9;  // WRITE of 2 bytes
constexpr std::size_t kReadRequestBytes = 8;
constexpr std::size_t kReadReplyBytes = 6 + kFeedbackCount;

std::uint16_t goal_for(std::uint64_t iteration) { return iteration % 2 == 0 ? 2000 : 2100; }

struct Transaction {
  std::string name;
  double wire_us;
};
const Transaction kWrite{"fc06_goal_position", wire_us(kWriteRequestBytes + kAckBytes) + kStsFastestReturnDelayUs};
const Transaction kRead{"fc03_feedback_block", wire_us(kReadRequestBytes + kReadReplyBytes) + kStsFastestReturnDelayUs};

// The same bus transaction without the gateway: flush, write, wait for `reply_bytes`.
LatencySummary direct_latency(sms::gateway::SerialPort& port, const sms::protocol::Bytes& frame,
                              std::size_t reply_bytes, std::chrono::milliseconds duration) {
  std::vector<std::uint32_t> samples;
  std::array<std::uint8_t, 256> buffer{};
  const auto end = Clock::now() + duration;
  while (Clock::now() < end) {
    if (!port.discard_input()) throw std::runtime_error("direct: flush failed");
    const auto before = Clock::now();
    if (!port.write_all(frame, 100ms)) throw std::runtime_error("direct: write failed");
    std::size_t received = 0;
    while (received < reply_bytes) {
      const auto readable = port.wait_readable(100ms);
      if (!readable || !*readable) throw std::runtime_error("direct: no reply from the simulated servo");
      const auto got = port.read_available(std::span(buffer).subspan(received));
      if (!got) throw std::runtime_error("direct: read failed: " + got.error());
      received += *got;
    }
    samples.push_back(to_ns(Clock::now() - before));
  }
  return summarize(samples);
}

struct Direct {
  LatencySummary write;
  LatencySummary read;
};

Direct measure_direct(std::chrono::milliseconds duration) {
  sms::simulator::SimulatedBus bus(sts_bus(1));
  start_precise(bus);
  set_return_delay(bus, 1, kStsFastestReturnDelay);
  sms::gateway::SerialPort port(sms::gateway::SerialSettings{bus.slave_path(), kBaud});
  if (const auto opened = port.open(); !opened) throw std::runtime_error("direct: " + opened.error());
  const std::uint8_t goal[] = {0xD0, 0x07};  // 2000, low byte first
  Direct direct;
  direct.write = direct_latency(
      port, sms::protocol::encode(sms::protocol::kFeetechFormat, sms::protocol::write(1, kGoalPositionAddress, goal)),
      kAckBytes, duration);
  direct.read = direct_latency(
      port,
      sms::protocol::encode(sms::protocol::kFeetechFormat, sms::protocol::read(1, kFeedbackAddress, kFeedbackCount)),
      kReadReplyBytes, duration);
  return direct;
}

void print_latency(const std::string& name, const LatencySummary& latency, double wire, const LatencySummary& direct) {
  print_figure(name + ".p50", latency.p50_us, "us");
  print_figure(name + ".p99", latency.p99_us, "us");
  print_figure(name + ".overhead_vs_wire.p50", latency.p50_us - wire, "us");
  print_figure(name + ".overhead_vs_wire.p99", latency.p99_us - wire, "us");
  print_figure(name + ".overhead_vs_direct.p50", latency.p50_us - direct.p50_us, "us");
  print_figure(name + ".overhead_vs_direct.p99", latency.p99_us - direct.p99_us, "us");
}

void measure_gateway(const std::string& mode, std::chrono::milliseconds poll_period, std::chrono::milliseconds duration,
                     const Direct& direct) {
  sms::simulator::SimulatedBus bus(sts_bus(1));
  start_precise(bus);
  set_return_delay(bus, 1, kStsFastestReturnDelay);
  GatewaySetup setup;
  setup.device = bus.slave_path();
  setup.servos = 1;
  setup.poll_period = poll_period;
  BenchGateway gateway(setup);
  gateway.wait_ready(1);
  std::this_thread::sleep_for(100ms);

  ClientTotals writes = run_clients(gateway.port(), 1, 1, duration, [](modbus_t* context, unsigned, std::uint64_t i) {
    return outcome_of(modbus_write_register(context, kGoalPositionAddress, goal_for(i)), 1);
  });
  const std::size_t write_count = writes.ok_ns.size();
  const auto applied = bus.read_field(1, "goal_position");
  ClientTotals reads = run_clients(gateway.port(), 1, 1, duration, [](modbus_t* context, unsigned, std::uint64_t) {
    std::array<std::uint16_t, kFeedbackCount> registers{};
    return outcome_of(modbus_read_registers(context, kFeedbackAddress, kFeedbackCount, registers.data()),
                      kFeedbackCount);
  });
  // A failed request is counted, not fatal: on a busy machine the simulator's thread can miss
  // the 20 ms response timeout a few times in a row (the gateway then answers 0x0B).
  for (const auto& [kind, totals] : {std::pair{kWrite.name, &writes}, std::pair{kRead.name, &reads}}) {
    if (totals->errors == 0) continue;
    print_figure("write_latency." + kind + ".gateway_" + mode + ".failed", static_cast<double>(totals->errors),
                 "requests");
    print_note(mode + ": first failure: " + totals->first_error);
  }
  // Without failures request i wrote goal_for(i): the last one acknowledged must be in the servo.
  if (writes.errors == 0 && write_count > 0 && applied != goal_for(write_count - 1)) {
    throw std::runtime_error(mode + ": the last acknowledged goal position is not in the servo");
  }
  print_latency("write_latency." + kWrite.name + ".gateway_" + mode, summarize(writes.ok_ns), kWrite.wire_us,
                direct.write);
  print_latency("write_latency." + kRead.name + ".gateway_" + mode, summarize(reads.ok_ns), kRead.wire_us, direct.read);
  gateway.stop();
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 3;
  if (const auto exit_status =
          parse_arguments(argc, argv,
                          "live FC06/FC03 latency through the gateway minus the modelled wire time and minus the "
                          "same transaction done directly on the pty",
                          {{"seconds", &seconds, "duration of each measurement"}})) {
    return *exit_status;
  }
  const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
  try {
    quiet_logs();
    print_note("one sts servo, 1 Mbaud, return delay 0, wire timing on; one libmodbus client, requests back to back");
    const Direct direct = measure_direct(duration);
    for (const auto& [transaction, latency] : {std::pair{kWrite, direct.write}, std::pair{kRead, direct.read}}) {
      const std::string name = "write_latency." + transaction.name;
      print_figure(name + ".wire_model", transaction.wire_us, "us");
      print_figure(name + ".direct_pty.p50", latency.p50_us, "us");
      print_figure(name + ".direct_pty.p99", latency.p99_us, "us");
    }
    measure_gateway("quiet_bus", std::chrono::hours{1}, duration, direct);
    measure_gateway("polling_20ms", 20ms, duration, direct);
  } catch (const std::exception& error) {
    std::cerr << "write_latency: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
