// rtu_slave_latency: what the upstream Modbus RTU port (docs/RTU_PANELS.md) adds between a
// panel and a servo. A simulated SMSMB servo at 115 200 bit/s (wire timing on, return delay 0),
// read with an 8-register FC03 (0x100..0x107) back to back, two ways:
//   direct   a libmodbus RTU master on the servo bus's pty (no gateway); the servo's t3.5 is
//            slept before each request, outside the timed part;
//   gateway  this program as the RTU master on a pty whose other end is an upstream port of a
//            Gateway in this process (the code sms-gateway runs), at 115 200 and 1 000 000
//            bit/s, the same FC03 to the servo's unit.
// A pty has no wire time, so the upstream wire time is only the silence the port must keep:
// t3.5 after the request before it may take the frame as ended (spec: 1.75 ms above 19 200
// bit/s). added_p50 = gateway p50 - direct p50 - t3.5: the gateway's own time (frame handling,
// the io thread, the router, the bus thread), the figure the 200 us target is about.
// Then a 10 Hz HMI poll: FC03 of 20 registers (0x180..0x193) at 115 200 bit/s for --hmi-seconds,
// counting errors.
//
//   rtu_slave_latency [--seconds 3] [--hmi-seconds 20]
#include <fcntl.h>
#include <modbus/modbus.h>
#include <poll.h>
#include <pty.h>
#include <sys/prctl.h>
#include <unistd.h>

#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_support.h"
#include "config/load.h"
#include "gateway/bus/rtu_master.h"
#include "gateway/gateway.h"
#include "gateway/rtu_slave/rtu_slave_port.h"
#include "protocol/modbus_rtu.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr std::uint32_t kBusRate = 115'200;
constexpr int kSlave = 1;
constexpr std::uint16_t kAddress = 0x100;
constexpr std::uint16_t kCount = 8;  // status .. present current: the feedback block
constexpr std::uint16_t kSmsmbReturnDelayRegister = 0x0C;

std::unique_ptr<sms::simulator::SimulatedBus> start_bus() {
  auto bus = std::make_unique<sms::simulator::SimulatedBus>(smsmb_bus(1, kBusRate));
  start_precise(*bus);
  const std::uint8_t zero[] = {0, 0};
  bus->write_memory(kSlave, kSmsmbReturnDelayRegister, zero);
  return bus;
}

std::vector<std::uint8_t> read_request(std::uint16_t address, std::uint16_t count) {
  return {0x03, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address & 0xFF), 0,
          static_cast<std::uint8_t>(count)};
}

// The master end of a pty whose slave end an upstream port opens: requests written here, the
// answer read back whole (its length is known: slave, 03, byte count, data, CRC).
class PanelLine {
 public:
  PanelLine() {
    int slave = -1;
    if (::openpty(&master_, &slave, nullptr, nullptr, nullptr) != 0) throw std::runtime_error("openpty failed");
    path_ = ::ttyname(slave);
    ::close(slave);  // the gateway opens it by name
  }
  ~PanelLine() { ::close(master_); }
  const std::string& path() const { return path_; }

  // One FC03; true when the whole answer came within `timeout` with a good CRC.
  bool read_registers(std::uint16_t address, std::uint16_t count, std::chrono::milliseconds timeout) {
    const auto request = sms::protocol::rtu::frame(kSlave, read_request(address, count));
    if (::write(master_, request.data(), request.size()) != static_cast<ssize_t>(request.size())) return false;
    const std::size_t expected = 5 + 2u * count;
    std::vector<std::uint8_t> answer;
    const auto deadline = Clock::now() + timeout;
    while (answer.size() < expected) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0) return false;
      pollfd fd{master_, POLLIN, 0};
      if (::poll(&fd, 1, static_cast<int>(left)) <= 0) return false;
      std::uint8_t buffer[512];
      const ssize_t n = ::read(master_, buffer, sizeof buffer);
      if (n <= 0) return false;
      answer.insert(answer.end(), buffer, buffer + n);
    }
    return answer.size() == expected && answer[1] == 0x03 &&
           sms::protocol::rtu::crc16(std::span(answer).first(expected - 2)) ==
               (answer[expected - 2] | answer[expected - 1] << 8);
  }

 private:
  int master_ = -1;
  std::string path_;
};

void print(const std::string& name, const LatencySummary& summary, std::uint64_t failures) {
  print_figure(name + ".requests", static_cast<double>(summary.count), "");
  print_figure(name + ".failures", static_cast<double>(failures), "");
  print_figure(name + ".p50", summary.p50_us, "us");
  print_figure(name + ".p99", summary.p99_us, "us");
}

LatencySummary direct(std::chrono::milliseconds duration) {
  auto bus = start_bus();
  modbus_t* context = modbus_new_rtu(bus->slave_path().c_str(), kBusRate, 'N', 8, 1);
  if (context == nullptr || modbus_connect(context) != 0) throw std::runtime_error("direct: cannot open the pty");
  modbus_set_slave(context, kSlave);
  modbus_set_response_timeout(context, 0, 200'000);
  const auto gap = sms::gateway::rtu_frame_gap(sms::gateway::SerialSettings{bus->slave_path(), kBusRate});
  std::vector<std::uint32_t> samples;
  std::uint64_t failures = 0;
  std::uint16_t registers[kCount];
  const auto end = Clock::now() + duration;
  while (Clock::now() < end) {
    std::this_thread::sleep_for(gap);  // the servo's t3.5, not timed
    const auto before = Clock::now();
    if (modbus_read_registers(context, kAddress, kCount, registers) == kCount) {
      samples.push_back(to_ns(Clock::now() - before));
    } else {
      ++failures;
    }
  }
  modbus_close(context);
  modbus_free(context);
  const auto summary = summarize(samples);
  print("rtu_slave_latency.direct_libmodbus_rtu", summary, failures);
  return summary;
}

// A gateway with the servo bus and one upstream port on `panel` at `rate`.
std::unique_ptr<sms::gateway::Gateway> start_gateway(const std::string& bus_device, const std::string& panel,
                                                     std::uint32_t rate) {
  const std::string yaml =
      "modbus_tcp: {listen: \"127.0.0.1:0\"}\n"
      "buses:\n"
      "  - {name: lift, device: \"" +
      bus_device + "\", protocol: modbus-rtu, baud: " + std::to_string(kBusRate) +
      ", poll_period_ms: 3600000, response_timeout_ms: 100}\n"  // no poll cycle competing with the panel
      "servos:\n"
      "  - {bus: lift, id: 1, table: smsmb}\n"
      "modbus_rtu_slave:\n"
      "  - {device: \"" +
      panel + "\", baud: " + std::to_string(rate) + "}\n";
  auto config = sms::config::load_config_string(yaml, "<rtu_slave_latency>");
  if (!config) throw std::runtime_error(config.error().to_string());
  auto gateway = std::make_unique<sms::gateway::Gateway>(std::move(*config));
  gateway->start();
  const auto deadline = Clock::now() + 20s;
  while (!(gateway->engine(0).bus_up() && !gateway->metrics().rtu_slaves.empty() &&
           gateway->metrics().rtu_slaves[0].open)) {
    if (Clock::now() > deadline) throw std::runtime_error("the gateway's bus or upstream port did not come up");
    std::this_thread::sleep_for(5ms);
  }
  return gateway;
}

void through_gateway(std::uint32_t rate, std::chrono::milliseconds duration, const LatencySummary& bare) {
  auto bus = start_bus();
  PanelLine panel;
  auto gateway = start_gateway(bus->slave_path(), panel.path(), rate);
  // Discovery done: the first read answers.
  const auto ready = Clock::now() + 10s;
  while (!panel.read_registers(kAddress, kCount, 500ms)) {
    if (Clock::now() > ready) throw std::runtime_error("no answer through the upstream port");
  }
  std::vector<std::uint32_t> samples;
  std::uint64_t failures = 0;
  const auto end = Clock::now() + duration;
  while (Clock::now() < end) {
    const auto before = Clock::now();
    if (panel.read_registers(kAddress, kCount, 500ms)) {
      samples.push_back(to_ns(Clock::now() - before));
    } else {
      ++failures;
    }
  }
  const auto summary = summarize(samples);
  const std::string name = "rtu_slave_latency.gateway_" + std::to_string(rate);
  print(name, summary, failures);
  const auto t35 = sms::gateway::rtu_slave_timing(sms::gateway::SerialSettings{panel.path(), rate}, {}).t35;
  const double t35_us = std::chrono::duration<double, std::micro>(t35).count();
  print_figure(name + ".upstream_t35", t35_us, "us");
  print_figure(name + ".added_p50", summary.p50_us - bare.p50_us - t35_us, "us");
  gateway->stop();
}

void hmi_poll(std::chrono::milliseconds duration) {
  auto bus = start_bus();
  PanelLine panel;
  auto gateway = start_gateway(bus->slave_path(), panel.path(), 115'200);
  const auto ready = Clock::now() + 10s;
  while (!panel.read_registers(0x180, 20, 500ms)) {
    if (Clock::now() > ready) throw std::runtime_error("no answer through the upstream port");
  }
  std::vector<std::uint32_t> samples;
  std::uint64_t errors = 0;
  auto next = Clock::now();
  const auto end = next + duration;
  while (next < end) {
    std::this_thread::sleep_until(next);
    const auto before = Clock::now();
    if (panel.read_registers(0x180, 20, 1s)) {
      samples.push_back(to_ns(Clock::now() - before));
    } else {
      ++errors;
    }
    next += 100ms;
  }
  const auto summary = summarize(samples);
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.polls", static_cast<double>(summary.count), "");
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.errors", static_cast<double>(errors), "");
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.p50", summary.p50_us, "us");
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.max", summary.max_us, "us");
  const auto stats = gateway->metrics().rtu_slaves.at(0);
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.crc_errors", static_cast<double>(stats.crc_errors), "");
  print_figure("rtu_slave_latency.hmi_10hz_20_registers.dropped_frames", static_cast<double>(stats.dropped_frames), "");
  gateway->stop();
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 3;
  double hmi_seconds = 20;
  if (const auto exit_status = parse_arguments(
          argc, argv, "the upstream RTU port's added latency, and a 10 Hz HMI poll through it",
          {{"seconds", &seconds, "per latency measurement"}, {"hmi-seconds", &hmi_seconds, "of the 10 Hz HMI poll"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    // The panel's side runs with the same 1 ns timer slack as the port's thread.
    ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
    print_figure("rtu_slave_latency.bus_wire", wire_us(8 + 5 + 2 * kCount, kBusRate), "us");
    const LatencySummary bare = direct(duration);
    for (const std::uint32_t rate : {115'200u, 1'000'000u}) through_gateway(rate, duration, bare);
    hmi_poll(std::chrono::milliseconds(static_cast<long>(hmi_seconds * 1000)));
  } catch (const std::exception& error) {
    std::cerr << "rtu_slave_latency: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
