// read_under_flood: the worst live read under a write flood: six clients write FC06
// to servos 1-6 back to back (each its own connection, as in the held-out run that starved a
// reader for 60 s), while a seventh reads FC03 of unit 1's feedback block; 6 sts servos at
// 1 000 000 baud with wire timing on, the real sms-gateway as a child process.
//
//   read_under_flood [--seconds 5]
//
// Printed: the reader's p50 / p99 / max latency and how many reads it got, the writers'
// throughput, and one bus transaction's time for scale (an FC06 is 150 us on the wire, the FC03
// of 15 registers 290 us, each + 100 us return delay: the fastest an sts servo answers). The rule (docs/DECISIONS.md
// "Gateway"): a client read waits at most 2 ms behind higher-priority work before it goes next, oldest first.
#include <modbus/modbus.h>

#include <algorithm>
#include <iostream>
#include <thread>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kServos = 6;
constexpr int kGoalPosition = 42;

}  // namespace

int main(int argc, char** argv) {
  double seconds = 5;
  if (const auto exit_status =
          parse_arguments(argc, argv, "worst live read latency while six clients flood the bus with writes",
                          {{"seconds", &seconds, "duration of the flood"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    sms::simulator::SimulatedBus bus(sts_bus(kServos));
    start_precise(bus);
    set_return_delay(bus, kServos, kStsFastestReturnDelay);
    GatewaySetup setup;
    setup.device = bus.slave_path();
    setup.servos = kServos;
    BenchGateway gateway(setup);
    gateway.wait_ready(kServos);
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));

    ClientTotals writers;
    std::thread flood([&] {
      // Writer i writes servo i + 1 (the unit is set per request).
      writers = run_clients(
          gateway.port(), 1, kServos, duration,
          [](modbus_t* context, unsigned client, std::uint64_t i) {
            modbus_set_slave(context, static_cast<int>(client + 1));
            const auto value = static_cast<std::uint16_t>(i % 2 == 0 ? 2000 : 2100);
            return outcome_of(modbus_write_register(context, kGoalPosition, value), 1);
          },
          10);
    });
    std::this_thread::sleep_for(200ms);  // the flood is on
    std::vector<std::uint32_t> reads_ns;
    std::uint64_t read_errors = 0;
    {
      ModbusClient reader(gateway.port(), 1, std::chrono::seconds{60});
      std::uint16_t registers[kFeedbackCount];
      const auto end = Clock::now() + duration - 400ms;
      while (Clock::now() < end) {
        const auto before = Clock::now();
        if (modbus_read_registers(reader.context(), kFeedbackAddress, kFeedbackCount, registers) == kFeedbackCount) {
          reads_ns.push_back(to_ns(Clock::now() - before));
        } else {
          ++read_errors;
        }
      }
    }
    flood.join();
    gateway.stop();

    const auto reads = summarize(reads_ns);
    const auto writes = summarize(writers.ok_ns);
    print_figure("read_under_flood.reads", static_cast<double>(reads.count), "");
    print_figure("read_under_flood.read_errors", static_cast<double>(read_errors), "");
    print_latency("read_under_flood.read", reads);
    print_figure("read_under_flood.writes_per_s", static_cast<double>(writes.count) / std::max(writers.seconds, 1e-9),
                 "req/s");
    print_figure("read_under_flood.write.p50", writes.p50_us, "us");
    print_figure("read_under_flood.write_busy_0x06", static_cast<double>(writers.busy_ns.size()), "");
    print_figure("read_under_flood.wire.fc03_feedback", wire_us(8 + 6 + kFeedbackCount) + kStsFastestReturnDelayUs,
                 "us");
  } catch (const std::exception& error) {
    std::cerr << "read_under_flood: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
