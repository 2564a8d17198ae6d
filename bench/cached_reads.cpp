// cached_reads: input-register reads served from the gateway's poll cache, next to a bare
// libmodbus TCP server answering the same request from a static map in the same run; then
// the bounded per-bus queue under a flood of live reads (bench (a)).
//
//   cached_reads [--seconds 3] [--flood-seconds 3]
//
// Both servers run as child processes of this program: the real sms-gateway (on 6 simulated
// sts servos at 1 Mbaud, the simulator running in this process) and this program again as
// `cached_reads --bare-server PORT`: one thread, a select() loop, modbus_receive + modbus_reply
// (libmodbus's own many-clients server pattern). The clients are libmodbus TCP clients, one
// thread and one connection each, reading unit 1's feedback block (FC04, address 56, 15
// registers) back to back. Everything shares the machine's cores.
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <signal.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <string>
#include <thread>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;

constexpr unsigned kClientCounts[] = {1, 8, 64};
constexpr unsigned kFloodClients = 64;
// Small enough that 64 synchronous clients overrun it (each has one request outstanding).
constexpr std::size_t kFloodQueueDepth = 32;
constexpr unsigned kServos = 6;

// --- the bare libmodbus server ---------------------------------------------------------------

int serve_bare(std::uint16_t port) {
  modbus_t* context = modbus_new_tcp("127.0.0.1", port);
  modbus_mapping_t* map = modbus_mapping_new_start_address(0, 0, 0, 0, 0, 0, kFeedbackAddress, kFeedbackCount);
  if (context == nullptr || map == nullptr) {
    std::cerr << "bare server: " << modbus_strerror(errno) << "\n";
    return 1;
  }
  for (int i = 0; i < kFeedbackCount; ++i) map->tab_input_registers[i] = static_cast<std::uint16_t>(2048 + i);
  const int listener = modbus_tcp_listen(context, 256);
  if (listener < 0) {
    std::cerr << "bare server: listen on 127.0.0.1:" << port << ": " << modbus_strerror(errno) << "\n";
    return 1;
  }
  fd_set open_sockets;
  FD_ZERO(&open_sockets);
  FD_SET(listener, &open_sockets);
  int highest = listener;
  std::array<std::uint8_t, MODBUS_TCP_MAX_ADU_LENGTH> query{};
  for (;;) {
    fd_set readable = open_sockets;
    if (::select(highest + 1, &readable, nullptr, nullptr, nullptr) < 0) {
      if (errno == EINTR) continue;
      std::cerr << "bare server: select: " << std::strerror(errno) << "\n";
      return 1;
    }
    for (int fd = 0; fd <= highest; ++fd) {
      if (!FD_ISSET(fd, &readable)) continue;
      if (fd == listener) {
        const int client = ::accept(listener, nullptr, nullptr);
        if (client < 0) continue;
        const int on = 1;
        ::setsockopt(client, IPPROTO_TCP, TCP_NODELAY, &on, sizeof on);
        if (client >= FD_SETSIZE) {
          ::close(client);
          continue;
        }
        FD_SET(client, &open_sockets);
        highest = std::max(highest, client);
        continue;
      }
      modbus_set_socket(context, fd);
      const int length = modbus_receive(context, query.data());
      if (length > 0) {
        modbus_reply(context, query.data(), length, map);
      } else if (length < 0) {
        ::close(fd);
        FD_CLR(fd, &open_sockets);
      }
    }
  }
}

// This program again, as `--bare-server PORT`, stopped with SIGTERM at the end.
class BareServerProcess {
 public:
  BareServerProcess()
      : port_(free_port()),
        process_({std::filesystem::read_symlink("/proc/self/exe").string(), "--bare-server", std::to_string(port_)}) {
    sms::test::await_or_throw(
        [&] {
          try {
            ModbusClient probe(port_, 1, 500ms);
            return probe.read_input(kFeedbackAddress, kFeedbackCount).ok();
          } catch (const std::exception&) {
            return false;
          }
        },
        "the bare server answering FC04 on 127.0.0.1:" + std::to_string(port_));
  }
  ~BareServerProcess() {
    process_.signal(SIGTERM);
    process_.wait_exit(sms::test::kAwaitTimeout);
  }
  BareServerProcess(const BareServerProcess&) = delete;
  BareServerProcess& operator=(const BareServerProcess&) = delete;
  std::uint16_t port() const { return port_; }

 private:
  std::uint16_t port_;
  sms::test::ChildProcess process_;
};

// --- measurements ------------------------------------------------------------------------------

Outcome read_feedback(modbus_t* context, unsigned, std::uint64_t) {
  std::array<std::uint16_t, kFeedbackCount> registers{};
  return outcome_of(modbus_read_input_registers(context, kFeedbackAddress, kFeedbackCount, registers.data()),
                    kFeedbackCount);
}

struct Throughput {
  double requests_per_s = 0;
  LatencySummary latency;
};

Throughput measure_reads(const std::string& server, std::uint16_t port, unsigned clients,
                         std::chrono::milliseconds duration) {
  ClientTotals totals = run_clients(port, 1, clients, duration, read_feedback);
  Throughput result;
  result.requests_per_s = static_cast<double>(totals.ok_ns.size()) / totals.seconds;
  result.latency = summarize(totals.ok_ns);
  const std::string name = "cached_reads." + server + ".clients_" + std::to_string(clients);
  print_figure(name + ".requests_per_s", result.requests_per_s, "req/s");
  print_latency(name, result.latency);
  if (totals.errors > 0) {
    print_figure(name + ".errors", static_cast<double>(totals.errors), "requests");
    print_note(name + ": first error: " + totals.first_error);
  }
  return result;
}

void measure_flood(std::uint16_t port, std::chrono::milliseconds duration, int nice) {
  // Live FC03 reads of the feedback block, spread over the six servos: every one is a bus READ.
  const auto live_read = [](modbus_t* context, unsigned client, std::uint64_t) {
    modbus_set_slave(context, static_cast<int>(1 + client % kServos));
    std::array<std::uint16_t, kFeedbackCount> registers{};
    return outcome_of(modbus_read_registers(context, kFeedbackAddress, kFeedbackCount, registers.data()),
                      kFeedbackCount);
  };
  ModbusClient observer(port, kGatewayUnit);
  const BusFacts before = read_bus_facts(observer);
  // Client operations go before polling, but a poll transaction waiting longer than one poll
  // period goes next: the cache age of unit 1 shows how far a sustained flood holds it back.
  std::atomic<bool> flooding{true};
  std::uint16_t max_cache_age_ms = 0;
  std::thread watcher([&] {
    ModbusClient watch(port, 1);
    while (flooding.load()) {
      try {
        max_cache_age_ms = std::max(max_cache_age_ms, read_servo_facts(watch, 1).cache_age_ms);
      } catch (const std::exception&) {
        // a 0x06 answer to the watcher itself: input registers never queue, so not expected
      }
      std::this_thread::sleep_for(50ms);
    }
  });
  ClientTotals totals = run_clients(port, 1, kFloodClients, duration, live_read, nice);
  flooding.store(false);
  watcher.join();
  const BusFacts after = read_bus_facts(observer);
  const double answered = static_cast<double>(totals.ok_ns.size());
  const double busy = static_cast<double>(totals.busy_ns.size());
  const LatencySummary ok = summarize(totals.ok_ns);
  const LatencySummary refused = summarize(totals.busy_ns);
  const std::string name = "queue_flood.clients_" + std::to_string(kFloodClients);
  print_figure(name + ".queue_depth", static_cast<double>(kFloodQueueDepth), "requests");
  print_figure(name + ".answered_per_s", answered / totals.seconds, "req/s");
  print_figure(name + ".busy_0x06", busy, "answers");
  print_figure(name + ".busy_fraction", 100.0 * busy / std::max(1.0, answered + busy), "%");
  print_figure(name + ".answered.p50", ok.p50_us, "us");
  print_figure(name + ".answered.p99", ok.p99_us, "us");
  print_figure(name + ".busy.p50", refused.p50_us, "us");
  print_figure(name + ".busy.p99", refused.p99_us, "us");
  print_figure(name + ".other_errors", static_cast<double>(totals.errors), "requests");
  print_figure(name + ".bus_frames_ok", after.frames_ok - before.frames_ok, "frames");
  print_figure(name + ".bus_timeouts", after.timeouts - before.timeouts, "frames");
  print_figure(name + ".bus_transaction_mean",
               1e6 * totals.seconds / std::max(1.0, static_cast<double>(after.frames_ok - before.frames_ok)), "us");
  print_figure(name + ".bus_transaction_wire_model", wire_us(8 + 6 + kFeedbackCount) + kStsFastestReturnDelayUs, "us");
  print_figure(name + ".servo1_cache_age_max", max_cache_age_ms, "ms");
  if (totals.errors > 0) print_note(name + ": first other error: " + totals.first_error);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc == 3 && std::string_view(argv[1]) == "--bare-server") {
    return serve_bare(static_cast<std::uint16_t>(std::stoi(argv[2])));
  }
  double seconds = 3;
  double flood_seconds = 3;
  // The flooding clients run at lower priority: 64 busy client threads at the simulator's
  // priority starve its thread on 2 cores, and late replies then look like silent servos
  // (on a real bus the servos are other hardware).
  double flood_nice = 10;
  if (const auto exit_status =
          parse_arguments(argc, argv,
                          "cached FC04 reads/s and latency with 1, 8 and 64 clients, gateway vs a bare libmodbus "
                          "server; then the bounded bus queue under 64 clients of live FC03 reads",
                          {{"seconds", &seconds, "duration of each throughput run"},
                           {"flood-seconds", &flood_seconds, "duration of the live-read flood"},
                           {"flood-nice", &flood_nice, "niceness of the flooding client threads"}})) {
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
    setup.request_queue_depth = kFloodQueueDepth;
    BenchGateway gateway(setup);
    gateway.wait_ready(kServos);
    BareServerProcess bare;
    print_note(
        "gateway: sms-gateway, 6 simulated sts servos at 1 Mbaud, poll period 20 ms; bare: libmodbus "
        "select() loop, static map; FC04 unit 1 address 56 count 15");

    for (const unsigned clients : kClientCounts) {
      const Throughput through_gateway = measure_reads("gateway", gateway.port(), clients, duration);
      const Throughput through_bare = measure_reads("bare_libmodbus", bare.port(), clients, duration);
      print_figure("cached_reads.ratio.clients_" + std::to_string(clients),
                   100.0 * through_gateway.requests_per_s / through_bare.requests_per_s, "%_of_bare");
    }
    measure_flood(gateway.port(), std::chrono::milliseconds(static_cast<long>(flood_seconds * 1000)),
                  static_cast<int>(flood_nice));
    if (const int status = gateway.stop(); status != 0) {
      std::cerr << "cached_reads: sms-gateway exited with status " << status << "\n";
      return 1;
    }
  } catch (const std::exception& error) {
    std::cerr << "cached_reads: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
