// forward_overhead: what `sms-gateway forward` adds to a Modbus-RTU transaction: a
// 10-register FC03 to one simulated SMSMB servo at 115 200 bit/s (wire timing on, return delay
// 0), back to back, two ways on the same kind of pty, for each --frame-gap setting (spec,
// 3.5chars, 500us):
//   direct      a plain libmodbus RTU master on the pty (no gateway), sleeping the same gap
//               before each request (libmodbus itself keeps none), with the same 1 ns timer
//               slack as the gateway's bus thread;
//   forward     a libmodbus TCP client -> ForwardGateway (the code `sms-gateway forward` runs,
//               in this process) -> the pty, with that --frame-gap.
// overhead_p50 = forward p50 - direct p50 with the same gap: what the gateway adds. The wire
// alone is 8 + 25 bytes = 2.86 ms; the gap is paid between transactions, so back-to-back
// requests show it: spec waits 1.75 ms above 19 200 bit/s, 3.5chars 0.30 ms.
//
//   forward_overhead [--seconds 2]
#include <modbus/modbus.h>
#include <sys/prctl.h>

#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"
#include "config/config.h"
#include "gateway/bus/rtu_master.h"
#include "gateway/units/passthrough.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr std::uint32_t kRate = 115'200;
constexpr int kSlave = 1;
constexpr int kAddress = 0x100;
constexpr int kCount = 10;
constexpr std::uint16_t kSmsmbReturnDelayRegister = 0x0C;

sms::simulator::SimulatedBus& start_bus(std::unique_ptr<sms::simulator::SimulatedBus>& bus) {
  bus = std::make_unique<sms::simulator::SimulatedBus>(smsmb_bus(1, kRate));
  start_precise(*bus);
  const std::uint8_t zero[] = {0, 0};
  bus->write_memory(kSlave, kSmsmbReturnDelayRegister, zero);
  return *bus;
}

// FC03 back to back on `context` for `duration`, each after `gap` (timed with it); failures
// counted, not timed.
LatencySummary read_loop(modbus_t* context, std::chrono::milliseconds duration, std::uint64_t& failures,
                         std::chrono::microseconds gap = {}) {
  std::vector<std::uint32_t> samples;
  std::uint16_t registers[kCount];
  const auto end = Clock::now() + duration;
  while (Clock::now() < end) {
    const auto before = Clock::now();
    if (gap.count() > 0) std::this_thread::sleep_for(gap);
    if (modbus_read_registers(context, kAddress, kCount, registers) == kCount) {
      samples.push_back(to_ns(Clock::now() - before));
    } else {
      ++failures;
    }
  }
  return summarize(samples);
}

void print(const std::string& name, const LatencySummary& summary, std::uint64_t failures) {
  print_figure(name + ".requests", static_cast<double>(summary.count), "");
  print_figure(name + ".failures", static_cast<double>(failures), "");
  print_figure(name + ".p50", summary.p50_us, "us");
  print_figure(name + ".p99", summary.p99_us, "us");
}

sms::config::FrameGap frame_gap(const std::string& setting) {
  const auto gap = sms::config::parse_frame_gap(setting);
  if (!gap) throw std::runtime_error(gap.error());
  return *gap;
}

LatencySummary direct(const std::string& gap_setting, std::chrono::milliseconds duration) {
  std::unique_ptr<sms::simulator::SimulatedBus> bus;
  start_bus(bus);
  modbus_t* context = modbus_new_rtu(bus->slave_path().c_str(), kRate, 'N', 8, 1);
  if (context == nullptr || modbus_connect(context) != 0) throw std::runtime_error("direct: cannot open the pty");
  modbus_set_slave(context, kSlave);
  modbus_set_response_timeout(context, 0, 200'000);
  // libmodbus sends the next request as soon as it has the answer; a slave that keeps its t3.5
  // (the simulator does) hears it as the tail of its own answer. The master keeps the same gap
  // as forward, timed as precisely (the gateway's bus thread runs with 1 ns timer slack).
  const auto gap = std::chrono::duration_cast<std::chrono::microseconds>(
      sms::gateway::rtu_frame_gap(sms::gateway::SerialSettings{bus->slave_path(), kRate}, frame_gap(gap_setting)));
  const int previous_slack = ::prctl(PR_GET_TIMERSLACK, 0UL, 0UL, 0UL, 0UL);
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
  std::uint64_t failures = 0;
  const auto summary = read_loop(context, duration, failures, gap);
  ::prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(previous_slack), 0UL, 0UL, 0UL);
  modbus_close(context);
  modbus_free(context);
  print("forward_overhead.direct_libmodbus_rtu.frame_gap_" + gap_setting, summary, failures);
  return summary;
}

void through_forward(const std::string& gap_setting, std::chrono::milliseconds duration, const LatencySummary& bare) {
  std::unique_ptr<sms::simulator::SimulatedBus> bus;
  start_bus(bus);
  sms::gateway::ForwardOptions options;
  options.serial = sms::gateway::SerialSettings{bus->slave_path(), kRate};
  options.listen = {"127.0.0.1", 0};
  options.rtu.frame_gap = frame_gap(gap_setting);
  sms::gateway::ForwardGateway forward(options);
  forward.start();
  while (!forward.engine().bus_up()) std::this_thread::sleep_for(5ms);
  ModbusClient client(forward.port(), kSlave);
  std::uint64_t failures = 0;
  const auto summary = read_loop(client.context(), duration, failures);
  const std::string name = "forward_overhead.forward.frame_gap_" + gap_setting;
  print(name, summary, failures);
  print_figure(name + ".overhead_p50", summary.p50_us - bare.p50_us, "us");
  forward.stop();
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 2;
  if (const auto exit_status =
          parse_arguments(argc, argv, "forward's overhead on a 10-register FC03 against a direct libmodbus RTU master",
                          {{"seconds", &seconds, "per measurement"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
    print_figure("forward_overhead.wire", wire_us(8 + 5 + 2 * kCount, kRate), "us");
    for (const std::string gap : {"spec", "3.5chars", "500us"}) {
      const LatencySummary bare = direct(gap, duration);
      through_forward(gap, duration, bare);
    }
  } catch (const std::exception& error) {
    std::cerr << "forward_overhead: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
