// console_stream: the browser console's cost (docs/CONSOLE.md, docs/PERFORMANCE.md "Browser
// console"): 20 sts servos polled at 50 Hz (poll_period_ms 20) by the real sms-gateway, first
// with no console client, then streamed to 5 open consoles — each a Beast WebSocket client of
// the overview (/ws/overview) and of one servo's page (/ws/servo/N, every poll of its block).
// Printed for both phases: the gateway's CPU (utime + stime from /proc, % of one core), the
// poll cycle (gateway unit register), the cached-read rate of one libmodbus client (FC04 back to
// back); for the streaming phase the time from the poll's store in the cache (the sample's own
// stamp, CLOCK_MONOTONIC) to its arrival at the client.
//
//   console_stream [--seconds 5]
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <iostream>
#include <mutex>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>

#include <modbus/modbus.h>
#include <boost/asio/connect.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/websocket.hpp>
#include <nlohmann/json.hpp>

#include "bench/bench_support.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = boost::asio::ip::tcp;

constexpr unsigned kServos = 20;
constexpr unsigned kConsoles = 5;

double cpu_seconds(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  std::istringstream fields(text.substr(text.rfind(')') + 2));
  std::string skip;
  for (int i = 0; i < 11; ++i) fields >> skip;  // state .. cmajflt: fields 3-13
  double utime = 0, stime = 0;
  fields >> utime >> stime;
  return (utime + stime) / static_cast<double>(sysconf(_SC_CLK_TCK));
}

struct Phase {
  double cpu_percent = 0;
  double cycle_us = 0;
  double reads_per_s = 0;
};

// CPU and poll cycle over `duration`, then the cached-read rate over another `duration`.
Phase measure(BenchGateway& gateway, std::chrono::milliseconds duration) {
  ModbusClient facts(gateway.port(), kGatewayUnit);
  std::vector<double> cycles;
  // CPU and poll cycle first, with no other Modbus client than this sampler (20 reads/s); then
  // the cached-read rate, whose client would otherwise dominate the gateway's CPU.
  const double cpu_before = cpu_seconds(gateway.pid());
  const auto start = Clock::now();
  while (Clock::now() - start < duration) {
    cycles.push_back(read_bus_facts(facts).last_poll_cycle_us);
    std::this_thread::sleep_for(50ms);
  }
  const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
  const double cpu_after = cpu_seconds(gateway.pid());
  const ClientTotals totals =
      run_clients(gateway.port(), 1, 1, duration, [](modbus_t* context, unsigned, std::uint64_t) {
        std::uint16_t registers[kFeedbackCount];
        return outcome_of(modbus_read_input_registers(context, kFeedbackAddress, kFeedbackCount, registers),
                          kFeedbackCount);
      });
  Phase phase;
  phase.cpu_percent = 100.0 * (cpu_after - cpu_before) / elapsed;
  std::sort(cycles.begin(), cycles.end());
  phase.cycle_us = cycles.empty() ? 0 : cycles[cycles.size() / 2];
  phase.reads_per_s = totals.ok_ns.size() / totals.seconds;
  return phase;
}

// The consoles' threads: how many have connected, and the first error one met (then it ended).
struct ConsoleClients {
  std::atomic<unsigned> connected{0};
  std::mutex mutex;
  std::string failure;
};

// One open console: the session cookie and CSRF token, then its two WebSockets, read until `stop`.
void console_client(std::uint16_t port, unsigned servo, std::atomic<bool>& stop, std::mutex& mutex,
                    std::vector<std::uint32_t>& latencies_ns, std::atomic<std::uint64_t>& messages,
                    ConsoleClients& clients) try {
  boost::asio::io_context io;
  tcp::resolver resolver(io);
  const auto endpoints = resolver.resolve("127.0.0.1", std::to_string(port));
  beast::tcp_stream stream(io);
  stream.connect(endpoints);
  http::request<http::empty_body> request(http::verb::get, "/api/session", 11);
  request.set(http::field::host, "127.0.0.1");
  http::write(stream, request);
  beast::flat_buffer buffer;
  http::response<http::string_body> response;
  http::read(stream, buffer, response);
  const std::string cookie = std::string(response[http::field::set_cookie])
                                 .substr(0, std::string(response[http::field::set_cookie]).find(';'));
  const std::string csrf = nlohmann::json::parse(response.body())["csrf"];
  std::vector<std::unique_ptr<websocket::stream<tcp::socket>>> sockets;
  for (const std::string& path : {std::string("/ws/overview"), "/ws/servo/" + std::to_string(servo)}) {
    auto socket = std::make_unique<websocket::stream<tcp::socket>>(io);
    boost::asio::connect(socket->next_layer(), endpoints);
    socket->set_option(websocket::stream_base::decorator(
        [&cookie](websocket::request_type& upgrade) { upgrade.set(http::field::cookie, cookie); }));
    socket->handshake("127.0.0.1", path + "?csrf=" + csrf);
    sockets.push_back(std::move(socket));
  }
  ++clients.connected;
  std::vector<std::thread> readers;
  for (auto& socket : sockets) {
    readers.emplace_back([&, raw = socket.get()] {
      beast::flat_buffer frames;
      beast::error_code error;
      while (!stop) {
        raw->read(frames, error);
        if (error) return;
        const auto arrived = Clock::now();
        ++messages;
        const auto message = nlohmann::json::parse(beast::buffers_to_string(frames.data()));
        frames.consume(frames.size());
        if (message["type"] != "samples") continue;
        std::lock_guard lock(mutex);
        for (const auto& row : message["samples"]) {
          const auto stored = Clock::time_point(std::chrono::microseconds(row[0].get<std::int64_t>()));
          latencies_ns.push_back(to_ns(arrived - stored));
        }
      }
    });
  }
  while (!stop) std::this_thread::sleep_for(20ms);
  for (auto& socket : sockets) {
    beast::error_code ignored;
    socket->next_layer().shutdown(tcp::socket::shutdown_both, ignored);
  }
  for (auto& reader : readers) reader.join();
} catch (const std::exception& error) {
  std::lock_guard lock(clients.mutex);
  if (clients.failure.empty()) clients.failure = "console of servo " + std::to_string(servo) + ": " + error.what();
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 5;
  if (const auto exit_status =
          parse_arguments(argc, argv, "the browser console's cost: 20 servos at 50 Hz streamed to 5 consoles",
                          {{"seconds", &seconds, "measuring time per phase"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    sms::simulator::SimulatedBus bus(sts_bus(kServos));
    start_precise(bus);
    set_return_delay(bus, kServos, kStsFastestReturnDelay);
    const std::uint16_t console_port = free_port();
    GatewaySetup setup;
    setup.device = bus.slave_path();
    setup.servos = kServos;
    setup.poll_period = 20ms;
    setup.extra_yaml = "console: {listen: \"127.0.0.1:" + std::to_string(console_port) + "\"}\n";
    BenchGateway gateway(setup);
    gateway.wait_ready(kServos);
    std::this_thread::sleep_for(500ms);
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
    print_note(
        "20 sts servos at 1 Mbaud polled every 20 ms; phase idle: no console client; phase streaming: 5 "
        "consoles, each /ws/overview + /ws/servo/N (every poll of one servo)");
    const Phase idle = measure(gateway, duration);

    std::atomic<bool> stop{false};
    std::mutex mutex;
    std::vector<std::uint32_t> latencies;
    std::atomic<std::uint64_t> messages{0};
    std::vector<std::thread> consoles;
    ConsoleClients clients;
    const auto failed = [&] {
      std::lock_guard lock(clients.mutex);
      return !clients.failure.empty();
    };
    // One console after another, as people open them: the console's door closes the oldest of
    // more than a few connections from one address still waiting for their first request, which
    // five consoles opened at the same instant on a loaded machine can be.
    for (unsigned i = 0; i < kConsoles; ++i) {
      consoles.emplace_back([&, i] {
        console_client(console_port, 1 + i * (kServos / kConsoles), stop, mutex, latencies, messages, clients);
      });
      const auto limit = std::chrono::steady_clock::now() + 30s;
      while (clients.connected.load() <= i && !failed() && std::chrono::steady_clock::now() < limit) {
        std::this_thread::sleep_for(5ms);
      }
    }
    const auto give_up_unless_all_streaming = [&] {
      if (clients.connected.load() == kConsoles && !failed()) return;
      stop = true;
      for (auto& console : consoles) console.join();
      throw std::runtime_error(clients.failure.empty()
                                   ? std::to_string(clients.connected.load()) + " of " + std::to_string(kConsoles) +
                                         " consoles connected within 30 s each"
                                   : clients.failure);
    };
    give_up_unless_all_streaming();   // a phase with fewer consoles would measure something else
    std::this_thread::sleep_for(1s);  // streaming
    {
      std::lock_guard lock(mutex);
      latencies.clear();
    }
    const auto counted_from = messages.load();
    const Phase streaming = measure(gateway, duration);
    const auto counted = messages.load() - counted_from;
    give_up_unless_all_streaming();
    stop = true;
    for (auto& console : consoles) console.join();

    print_figure("console.idle.gateway_cpu", idle.cpu_percent, "%");
    print_figure("console.streaming.gateway_cpu", streaming.cpu_percent, "%");
    print_figure("console.extra_cpu", streaming.cpu_percent - idle.cpu_percent, "%");
    print_figure("console.idle.poll_cycle_median", idle.cycle_us, "us");
    print_figure("console.streaming.poll_cycle_median", streaming.cycle_us, "us");
    print_figure("console.idle.cached_reads", idle.reads_per_s, "req/s");
    print_figure("console.streaming.cached_reads", streaming.reads_per_s, "req/s");
    print_figure("console.streaming.messages", counted / seconds, "msg/s");
    LatencySummary summary;
    {
      std::lock_guard lock(mutex);
      summary = summarize(latencies);
    }
    print_figure("console.streaming.samples", static_cast<double>(summary.count), "samples");
    print_latency("console.poll_to_client", summary, LatencyUnit::Ms);
    gateway.stop();
  } catch (const std::exception& error) {
    std::cerr << "console_stream: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
