// console_login_flood: a logged-in operator's e-stop while the browser console is flooded with
// wrong passwords (docs/CONSOLE.md "Logins", docs/PERFORMANCE.md "Browser console logins"). The
// real sms-gateway on 3 simulated sts servos, its console on 127.0.0.1 with one operate user; the
// operator's browser is one keep-alive connection that latches the e-stop (POST /api/estop),
// resets it and asks for its session (GET /api/session), again and again, first with nothing else
// going on, then while 16 threads send logins with wrong passwords back to back. Each flood
// request comes from a new loopback address (127.T.x.y, T the thread) with a new user name, so
// neither the per-address nor the per-user backoff holds it up: every one asks the gateway for a
// password check (Argon2id), the worst case. The flooding threads run at nice 19: an attacker's
// CPU is another machine's. Printed for both phases: the e-stop POST's latency (send to whole
// answer; it answers once the stop frames are on the wire), GET /api/session's (the console
// thread alone), the same e-stop latched by a Modbus client (no console in its way: what the bus
// path itself takes on this machine meanwhile), the gateway's CPU, and the flood's answers per
// second by status.
//
//   console_login_flood [--seconds 10] [--flooders 16] [--quick]
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cstring>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>

#include "bench/bench_support.h"
#include "gateway/console/console_access.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;
namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using tcp = asio::ip::tcp;

constexpr unsigned kServos = 3;
constexpr std::string_view kPassword = "operator's own password";
constexpr double kQuickSeconds = 3;
// Latch, then reset, once per period: an operator pressing far more often than any real one.
constexpr auto kPressPeriod = 50ms;
constexpr int kEstopCoil = 1;  // of the gateway unit (docs/PLC_GUIDE.md "Safety")

// CPU time of a process so far (utime + stime from /proc), s.
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

// One HTTP/1.1 exchange on an open stream; the answer's status and body.
http::response<http::string_body> exchange(beast::tcp_stream& stream, http::request<http::string_body>& request) {
  request.prepare_payload();
  http::write(stream, request);
  beast::flat_buffer buffer;
  http::response<http::string_body> response;
  http::read(stream, buffer, response);
  return response;
}

http::request<http::string_body> post(std::string_view target, std::string body) {
  http::request<http::string_body> request(http::verb::post, std::string(target), 11);
  request.set(http::field::host, "127.0.0.1");
  request.set(http::field::content_type, "application/json");
  request.body() = std::move(body);
  return request;
}

// The operator: a session (cookie, CSRF token) on one keep-alive connection, as a browser has.
class Operator {
 public:
  explicit Operator(std::uint16_t port) : stream_(io_) {
    stream_.connect(tcp::endpoint(asio::ip::make_address("127.0.0.1"), port));
    auto login = post("/api/login", nlohmann::json{{"user", "op"}, {"password", kPassword}}.dump());
    const auto answer = exchange(stream_, login);
    if (answer.result_int() != 200) {
      throw std::runtime_error("the operator's login was refused (HTTP " + std::to_string(answer.result_int()) +
                               "): " + answer.body());
    }
    const std::string cookie(answer[http::field::set_cookie]);
    cookie_ = cookie.substr(0, cookie.find(';'));
    csrf_ = nlohmann::json::parse(answer.body()).at("csrf").get<std::string>();
  }

  // One e-stop POST, latch or reset; its latency. Throws when it is not carried out.
  Clock::duration press(bool latch) {
    auto request = post("/api/estop", nlohmann::json{{"latch", latch}}.dump());
    request.set(http::field::cookie, cookie_);
    request.set("X-CSRF-Token", csrf_);
    const auto start = Clock::now();
    const auto answer = exchange(stream_, request);
    const auto took = Clock::now() - start;
    if (answer.result_int() != 200) {
      throw std::runtime_error("the e-stop POST was answered HTTP " + std::to_string(answer.result_int()) + ": " +
                               answer.body());
    }
    return took;
  }

  // GET /api/session: the console thread's own answer, no bus and no other thread behind it.
  Clock::duration look() {
    http::request<http::string_body> request(http::verb::get, "/api/session", 11);
    request.set(http::field::host, "127.0.0.1");
    request.set(http::field::cookie, cookie_);
    const auto start = Clock::now();
    const auto answer = exchange(stream_, request);
    const auto took = Clock::now() - start;
    if (answer.result_int() != 200) {
      throw std::runtime_error("GET /api/session was answered HTTP " + std::to_string(answer.result_int()));
    }
    return took;
  }

 private:
  asio::io_context io_;
  beast::tcp_stream stream_;
  std::string cookie_;
  std::string csrf_;
};

struct Presses {
  std::vector<std::uint32_t> latches;  // the e-stop latch POSTs' latencies
  std::vector<std::uint32_t> looks;    // GET /api/session's
  std::vector<std::uint32_t> modbus;   // the same e-stop latched by a Modbus client (coil 1 of unit 255)
};

// Latches the e-stop from the console and resets it, asks for the session, and latches and resets
// it over Modbus, every kPressPeriod for `duration`.
Presses press_for(Operator& person, ModbusClient& plc, std::chrono::milliseconds duration) {
  Presses presses;
  const auto end = Clock::now() + duration;
  auto next = Clock::now();
  while (Clock::now() < end) {
    presses.latches.push_back(to_ns(person.press(true)));
    (void)person.press(false);
    presses.looks.push_back(to_ns(person.look()));
    const auto start = Clock::now();
    plc.write_coil(kEstopCoil, true).or_throw("the Modbus e-stop (coil 1 := 1)");
    presses.modbus.push_back(to_ns(Clock::now() - start));
    plc.write_coil(kEstopCoil, false).or_throw("the Modbus e-stop reset (coil 1 := 0)");
    next += kPressPeriod;
    std::this_thread::sleep_until(next);
  }
  return presses;
}

struct FloodTotals {
  std::mutex mutex;
  std::map<unsigned, std::uint64_t> statuses;  // HTTP status -> answers
  std::uint64_t failures = 0;                  // no answer (connection refused or closed)
  std::string first_failure;
};

// One flooding thread: a new connection from a new loopback address, with a new user name and a
// wrong password, for each login, until `stop`.
void flood(unsigned thread, std::uint16_t port, const std::atomic<bool>& stop, FloodTotals& totals) {
  // Below the gateway and the simulated servos: on a real network the attacker is another machine.
  setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), 19);
  asio::io_context io;
  std::map<unsigned, std::uint64_t> statuses;
  std::uint64_t failures = 0;
  std::string first_failure;
  for (std::uint32_t i = 0; !stop; ++i) {
    const auto source = asio::ip::make_address_v4(std::array<unsigned char, 4>{
        127, static_cast<unsigned char>(1 + thread), static_cast<unsigned char>((i >> 8) & 0xFF),
        static_cast<unsigned char>(1 + i % 254)});
    try {
      beast::tcp_stream stream(io);
      stream.socket().open(tcp::v4());
      stream.socket().bind(tcp::endpoint(source, 0));
      stream.expires_after(10s);
      stream.connect(tcp::endpoint(asio::ip::make_address("127.0.0.1"), port));
      auto login =
          post("/api/login", nlohmann::json{{"user", "guess-" + std::to_string(thread) + "-" + std::to_string(i)},
                                            {"password", "wrong password " + std::to_string(i)}}
                                 .dump());
      login.keep_alive(false);
      const auto answer = exchange(stream, login);
      ++statuses[answer.result_int()];
    } catch (const std::exception& error) {
      if (failures++ == 0) first_failure = error.what();
      std::this_thread::sleep_for(1ms);  // the console closed a connection over its limit
    }
  }
  std::lock_guard lock(totals.mutex);
  for (const auto& [status, count] : statuses) totals.statuses[status] += count;
  totals.failures += failures;
  if (totals.first_failure.empty()) totals.first_failure = first_failure;
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 10;
  double flooders = 16;
  // --quick (no value) is taken out before the `--name value` options are parsed.
  bool quick = false;
  std::vector<char*> arguments;
  for (int i = 0; i < argc; ++i) {
    if (i > 0 && std::strcmp(argv[i], "--quick") == 0) {
      quick = true;
    } else {
      arguments.push_back(argv[i]);
    }
  }
  if (const auto exit_status =
          parse_arguments(static_cast<int>(arguments.size()), arguments.data(),
                          "a logged-in operator's e-stop POST latency, idle and during a wrong-password flood of the "
                          "browser console; --quick: " +
                              std::to_string(static_cast<int>(kQuickSeconds)) + " s per phase",
                          {{"seconds", &seconds, "measuring time per phase"},
                           {"flooders", &flooders, "threads sending wrong passwords, 1-64"}})) {
    return *exit_status;
  }
  if (quick) seconds = std::min(seconds, kQuickSeconds);
  if (seconds < 1 || flooders < 1 || flooders > 64) {
    std::cerr << "console_login_flood: --seconds must be at least 1 and --flooders 1-64\n";
    return 2;
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
    setup.extra_yaml = "console:\n  listen: \"127.0.0.1:" + std::to_string(console_port) +
                       "\"\n  users:\n    - {name: op, role: operate, password_hash: \"" +
                       sms::gateway::console::hash_password(kPassword) + "\"}\n";
    BenchGateway gateway(setup);
    gateway.wait_ready(kServos);
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
    print_note(
        "sms-gateway child, 3 sts servos at 1 Mbaud; an operate user's e-stop POST (latch, then reset, then GET "
        "/api/session, every " +
        std::to_string(kPressPeriod.count()) +
        " ms) on one keep-alive connection; flood: " + std::to_string(static_cast<int>(flooders)) +
        " threads (nice 10), each login a new connection from a new 127.T.x.y address with a new user "
        "name and a wrong password");

    Operator person(console_port);
    ModbusClient plc(gateway.port(), kGatewayUnit);
    double cpu_from = cpu_seconds(gateway.pid());
    auto begin = Clock::now();
    auto idle = press_for(person, plc, duration);
    const double idle_cpu =
        100.0 * (cpu_seconds(gateway.pid()) - cpu_from) / std::chrono::duration<double>(Clock::now() - begin).count();

    std::atomic<bool> stop{false};
    FloodTotals totals;
    const auto flood_begin = Clock::now();
    std::vector<std::thread> threads;
    for (unsigned t = 0; t < static_cast<unsigned>(flooders); ++t)
      threads.emplace_back([&, t] { flood(t, console_port, stop, totals); });
    std::this_thread::sleep_for(500ms);  // the flood under way
    Presses flooded;
    std::string operator_failure;
    cpu_from = cpu_seconds(gateway.pid());
    begin = Clock::now();
    try {
      flooded = press_for(person, plc, duration);
    } catch (const std::exception& error) {
      operator_failure = error.what();
    }
    const double flood_cpu =
        100.0 * (cpu_seconds(gateway.pid()) - cpu_from) / std::chrono::duration<double>(Clock::now() - begin).count();
    stop = true;
    for (auto& thread : threads) thread.join();
    const double flood_seconds = std::chrono::duration<double>(Clock::now() - flood_begin).count();

    print_latency("console_login_flood.idle.estop", summarize(idle.latches), LatencyUnit::Ms);
    print_latency("console_login_flood.idle.session_get", summarize(idle.looks), LatencyUnit::Ms);
    print_latency("console_login_flood.idle.modbus_estop", summarize(idle.modbus), LatencyUnit::Ms);
    if (!operator_failure.empty()) {
      print_note("the operator's e-stop failed during the flood: " + operator_failure);
      print_figure("console_login_flood.flood.estop_failed", 1, "");
    } else {
      print_latency("console_login_flood.flood.estop", summarize(flooded.latches), LatencyUnit::Ms);
      print_latency("console_login_flood.flood.session_get", summarize(flooded.looks), LatencyUnit::Ms);
      print_latency("console_login_flood.flood.modbus_estop", summarize(flooded.modbus), LatencyUnit::Ms);
    }
    std::uint64_t answered = 0;
    for (const auto& [status, count] : totals.statuses) {
      answered += count;
      print_figure("console_login_flood.flood.http_" + std::to_string(status), count / flood_seconds, "req/s");
    }
    print_figure("console_login_flood.flood.logins", answered / flood_seconds, "req/s");
    print_figure("console_login_flood.idle.gateway_cpu", idle_cpu, "%");
    print_figure("console_login_flood.flood.gateway_cpu", flood_cpu, "%");
    print_figure("console_login_flood.flood.unanswered", totals.failures / flood_seconds, "req/s");
    if (!totals.first_failure.empty()) print_note("first unanswered login: " + totals.first_failure);
    gateway.stop();
    if (!operator_failure.empty()) return 1;
  } catch (const std::exception& error) {
    std::cerr << "console_login_flood: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
