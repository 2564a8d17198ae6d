#include "bench/bench_support.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <latch>
#include <sstream>
#include <stdexcept>
#include <thread>

#include <spdlog/spdlog.h>

extern char** environ;

namespace sms::bench {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

// --- output ----------------------------------------------------------------------------------

void print_figure(std::string_view name, double value, std::string_view unit) {
  const double magnitude = std::fabs(value);
  const int decimals = magnitude >= 1000 || value == std::floor(value) ? 0 : magnitude >= 10 ? 1 : 3;
  std::printf("%.*s %.*f %.*s\n", static_cast<int>(name.size()), name.data(), decimals, value,
              static_cast<int>(unit.size()), unit.data());
  std::fflush(stdout);
}

void print_note(std::string_view text) {
  std::printf("# %.*s\n", static_cast<int>(text.size()), text.data());
  std::fflush(stdout);
}

// --- latency ---------------------------------------------------------------------------------

void print_latency(const std::string& name, const LatencySummary& summary, LatencyUnit unit, bool with_max) {
  const double scale = unit == LatencyUnit::Ms ? 1e-3 : 1.0;
  const std::string_view label = unit == LatencyUnit::Ms ? "ms" : "us";
  print_figure(name + ".p50", summary.p50_us * scale, label);
  print_figure(name + ".p99", summary.p99_us * scale, label);
  if (with_max) print_figure(name + ".max", summary.max_us * scale, label);
}

LatencySummary summarize(std::vector<std::uint32_t>& samples_ns) {
  LatencySummary summary;
  summary.count = samples_ns.size();
  if (samples_ns.empty()) return summary;
  std::sort(samples_ns.begin(), samples_ns.end());
  const auto at = [&](double fraction) {
    const auto index = static_cast<std::size_t>(fraction * static_cast<double>(samples_ns.size() - 1));
    return static_cast<double>(samples_ns[index]) / 1000.0;
  };
  summary.p50_us = at(0.50);
  summary.p99_us = at(0.99);
  summary.max_us = static_cast<double>(samples_ns.back()) / 1000.0;
  return summary;
}

std::uint32_t to_ns(Clock::duration duration) {
  const auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(duration).count();
  return static_cast<std::uint32_t>(std::clamp<std::int64_t>(ns, 0, UINT32_MAX));
}

// --- the bus -----------------------------------------------------------------------------------

double wire_us(std::size_t bytes, std::uint32_t baud) {
  return static_cast<double>(bytes) * kBitsPerCharacter * 1e6 / static_cast<double>(baud);
}

simulator::BusOptions sts_bus(unsigned count) {
  simulator::BusOptions options;
  for (unsigned id = 1; id <= count; ++id) {
    options.servos.push_back(simulator::ServoConfig{static_cast<std::uint8_t>(id), modbus_map::TableId::Sts,
                                                    protocol::BusProtocol::Feetech, kBaud});
  }
  options.timing = true;
  options.seed = 1;
  return options;
}

simulator::BusOptions smsmb_bus(unsigned count, std::uint32_t baud) {
  simulator::BusOptions options;
  for (unsigned id = 1; id <= count; ++id) {
    options.servos.push_back(simulator::ServoConfig{static_cast<std::uint8_t>(id), modbus_map::TableId::Smsmb,
                                                    protocol::BusProtocol::ModbusRtu, baud});
  }
  options.timing = true;
  options.seed = 1;
  return options;
}

void set_return_delay(simulator::SimulatedBus& bus, unsigned count, std::uint8_t units) {
  const std::uint8_t value[] = {units};
  for (unsigned id = 1; id <= count; ++id) {
    if (!bus.write_memory(static_cast<std::uint8_t>(id), kReturnDelayAddress, value)) {
      throw std::runtime_error("simulated servo " + std::to_string(id) + ": cannot set its return delay");
    }
  }
}

// --- the gateway as a child process ----------------------------------------------------------

std::string gateway_yaml(const GatewaySetup& setup, std::uint16_t port) {
  std::ostringstream yaml;
  yaml << "# written by the sms-gateway benchmarks\n"
       << "modbus_tcp:\n"
       << "  listen: 127.0.0.1:" << port << "\n"
       << "  max_connections: " << setup.max_connections << "\n"
       << "  idle_timeout_s: 0\n"
       << "  request_queue_depth: " << setup.request_queue_depth << "\n"
       << "buses:\n"
       << "  - name: bench\n"
       << "    device: \"" << setup.device << "\"\n"
       << "    protocol: " << (setup.modbus_rtu_baud != 0 ? "modbus-rtu" : "feetech") << "\n"
       << "    baud: " << (setup.modbus_rtu_baud != 0 ? setup.modbus_rtu_baud : kBaud) << "\n"
       << "    poll_period_ms: " << setup.poll_period.count() << "\n"
       << "    offline_probe_period_ms: " << setup.probe_period.count() << "\n";
  if (setup.watchdog) yaml << "    watchdog: {timeout_ms: " << setup.watchdog->count() << ", feed: any_write}\n";
  if (setup.modbus_rtu_baud != 0) yaml << "    frame_gap: " << setup.frame_gap << "\n";
  yaml << "servos:\n";
  const char* table = setup.modbus_rtu_baud != 0 ? "smsmb" : "sts";
  for (unsigned id = 1; id <= setup.servos; ++id) yaml << "  - {bus: bench, id: " << id << ", table: " << table << "}\n";
  yaml << "logging:\n  level: warn\n" << setup.extra_yaml;
  return yaml.str();
}

std::uint16_t free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = 0;
  socklen_t length = sizeof address;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) != 0) {
    const int error = errno;
    ::close(fd);
    throw std::runtime_error(std::string("cannot find a free port on 127.0.0.1: ") + std::strerror(error));
  }
  ::close(fd);
  return ntohs(address.sin_port);
}

std::string gateway_program() {
  if (const char* chosen = std::getenv("SMS_GATEWAY"); chosen != nullptr && *chosen != '\0') return chosen;
  const fs::path self = fs::read_symlink("/proc/self/exe");
  const fs::path beside = self.parent_path() / "sms-gateway";
  if (::access(beside.c_str(), X_OK) != 0) {
    throw std::runtime_error(beside.string() +
                             " not found: build it first (cmake --build build --target sms-gateway), or set "
                             "SMS_GATEWAY to the program to measure");
  }
  return beside.string();
}

GatewayProcess::GatewayProcess(const GatewaySetup& setup) {
  const std::string program = gateway_program();
  std::string pattern = (fs::temp_directory_path() / "sms-bench-XXXXXX").string();
  if (::mkdtemp(pattern.data()) == nullptr) {
    throw std::runtime_error("mkdtemp " + pattern + ": " + std::strerror(errno));
  }
  directory_ = pattern;
  const std::string config_path = directory_ + "/gateway.yaml";
  log_path_ = directory_ + "/gateway.log";
  port_ = free_port();
  {
    std::ofstream config(config_path);
    config << gateway_yaml(setup, port_);
    if (!config) throw std::runtime_error("cannot write " + config_path);
  }

  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, log_path_.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&actions, STDOUT_FILENO, STDERR_FILENO);
  std::vector<std::string> arguments{program, "--config", config_path, "--log-level", "warn"};
  std::vector<char*> argv;
  for (auto& argument : arguments) argv.push_back(argument.data());
  argv.push_back(nullptr);
  const int spawned = ::posix_spawn(&pid_, program.c_str(), &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (spawned != 0) {
    pid_ = -1;
    throw std::runtime_error("cannot start " + program + ": " + std::strerror(spawned));
  }
}

GatewayProcess::~GatewayProcess() {
  if (pid_ > 0) stop();
  if (std::getenv("SMS_BENCH_KEEP") == nullptr) {
    std::error_code ignored;
    fs::remove_all(directory_, ignored);
  } else {
    std::cerr << "gateway files kept in " << directory_ << "\n";
  }
}

std::string GatewayProcess::log_tail() const {
  std::ifstream log(log_path_);
  std::vector<std::string> lines;
  for (std::string line; std::getline(log, line);) lines.push_back(line);
  std::string tail;
  for (std::size_t i = lines.size() > 15 ? lines.size() - 15 : 0; i < lines.size(); ++i) tail += "  " + lines[i] + "\n";
  return tail.empty() ? "  (the gateway logged nothing)\n" : tail;
}

void GatewayProcess::wait_ready(unsigned online, std::chrono::seconds limit) {
  const auto deadline = Clock::now() + limit;
  std::string last_state = "no connection yet";
  while (Clock::now() < deadline) {
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      throw std::runtime_error("sms-gateway exited during start-up (status " + std::to_string(status) +
                               "); its log:\n" + log_tail());
    }
    try {
      ModbusClient client(port_, kGatewayUnit, 500ms);
      const BusFacts facts = read_bus_facts(client);
      if (facts.state == 1 && facts.servos_online == online && facts.last_poll_cycle_us > 0) return;
      last_state = "bus state " + std::to_string(facts.state) + ", " + std::to_string(facts.servos_online) +
                   " servos online, last poll cycle " + std::to_string(facts.last_poll_cycle_us) + " us";
    } catch (const std::exception& error) {
      last_state = error.what();
    }
    std::this_thread::sleep_for(50ms);
  }
  throw std::runtime_error("sms-gateway on port " + std::to_string(port_) + " not ready after " +
                           std::to_string(limit.count()) + " s (wanted " + std::to_string(online) +
                           " servos online; last seen: " + last_state + "); its log:\n" + log_tail());
}

int GatewayProcess::stop() {
  if (pid_ <= 0) return -1;
  ::kill(pid_, SIGTERM);
  int status = 0;
  const auto deadline = Clock::now() + 10s;
  while (::waitpid(pid_, &status, WNOHANG) == 0) {
    if (Clock::now() > deadline) {
      std::cerr << "sms-gateway (pid " << pid_ << ") ignored SIGTERM for 10 s: killing it\n";
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, &status, 0);
      break;
    }
    std::this_thread::sleep_for(10ms);
  }
  pid_ = -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

namespace {

std::optional<std::uint64_t> status_field_kib(pid_t pid, std::string_view key) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  if (!status) return std::nullopt;
  for (std::string line; std::getline(status, line);) {
    if (line.rfind(key, 0) != 0) continue;
    std::istringstream fields(line.substr(key.size()));
    std::uint64_t kib = 0;
    if (fields >> kib) return kib;
  }
  return std::nullopt;
}

}  // namespace

std::optional<std::uint64_t> rss_kib(pid_t pid) { return status_field_kib(pid, "VmRSS:"); }

std::optional<std::uint64_t> open_fds(pid_t pid) {
  std::error_code error;
  fs::directory_iterator entries("/proc/" + std::to_string(pid) + "/fd", error);
  if (error) return std::nullopt;
  std::uint64_t count = 0;
  for (const auto& entry : entries) {
    (void)entry;
    ++count;
  }
  return count;
}

// --- libmodbus clients -----------------------------------------------------------------------

std::string modbus_error_text() { return modbus_strerror(errno); }

ModbusClient::ModbusClient(std::uint16_t port, int unit, std::chrono::milliseconds response_timeout)
    : context_(modbus_new_tcp("127.0.0.1", port)) {
  if (context_ == nullptr) throw std::runtime_error("modbus_new_tcp: " + modbus_error_text());
  const auto us = response_timeout.count() * 1000;
  modbus_set_response_timeout(context_, static_cast<std::uint32_t>(us / 1'000'000),
                              static_cast<std::uint32_t>(us % 1'000'000));
  set_unit(unit);
  if (modbus_connect(context_) != 0) {
    const std::string error = modbus_error_text();
    modbus_free(context_);
    throw std::runtime_error("connect to 127.0.0.1:" + std::to_string(port) + ": " + error);
  }
}

ModbusClient::~ModbusClient() {
  modbus_close(context_);
  modbus_free(context_);
}

void ModbusClient::set_unit(int unit) {
  if (modbus_set_slave(context_, unit) != 0) {
    throw std::runtime_error("unit " + std::to_string(unit) + ": " + modbus_error_text());
  }
}

std::vector<std::uint16_t> ModbusClient::input_registers(int address, int count) {
  std::vector<std::uint16_t> registers(static_cast<std::size_t>(count));
  if (modbus_read_input_registers(context_, address, count, registers.data()) != count) {
    throw std::runtime_error("FC04 " + std::to_string(address) + "+" + std::to_string(count) + ": " +
                             modbus_error_text());
  }
  return registers;
}

std::vector<std::uint16_t> ModbusClient::holding_registers(int address, int count) {
  std::vector<std::uint16_t> registers(static_cast<std::size_t>(count));
  if (modbus_read_registers(context_, address, count, registers.data()) != count) {
    throw std::runtime_error("FC03 " + std::to_string(address) + "+" + std::to_string(count) + ": " +
                             modbus_error_text());
  }
  return registers;
}

BusFacts read_bus_facts(ModbusClient& client) {
  client.set_unit(kGatewayUnit);
  const auto r = client.input_registers(100, 10);  // bus 0: 100 + 20 * 0
  return BusFacts{r[0], r[2], r[3], u32(r[4], r[5]), u32(r[6], r[7]), u32(r[8], r[9])};
}

ServoFacts read_servo_facts(ModbusClient& client, int unit) {
  client.set_unit(unit);
  const auto r = client.input_registers(1000, 8);
  return ServoFacts{r[1] != 0, r[2], u32(r[4], r[5]), u32(r[6], r[7])};
}

Outcome outcome_of(int rc, int expected) {
  if (rc == expected) return Outcome::Ok;
  if (rc < 0 && errno == EMBXSBUSY) return Outcome::Busy;
  return Outcome::Error;
}

ClientTotals run_clients(std::uint16_t port, int unit, unsigned clients, std::chrono::milliseconds duration,
                         const RequestFn& request, int nice) {
  std::vector<ClientTotals> per_client(clients);
  std::vector<Clock::time_point> ended(clients);
  std::latch connected(clients);
  std::latch go(1);
  Clock::time_point start;
  Clock::time_point deadline;

  std::vector<std::thread> threads;
  threads.reserve(clients);
  for (unsigned index = 0; index < clients; ++index) {
    threads.emplace_back([&, index] {
      ClientTotals& totals = per_client[index];
      if (nice > 0) ::setpriority(PRIO_PROCESS, static_cast<id_t>(::gettid()), nice);
      std::optional<ModbusClient> client;
      try {
        client.emplace(port, unit);
      } catch (const std::exception& error) {
        totals.errors = 1;
        totals.first_error = error.what();
      }
      totals.ok_ns.reserve(1 << 16);
      connected.count_down();
      go.wait();
      if (client) {
        for (std::uint64_t iteration = 0;; ++iteration) {
          const auto before = Clock::now();
          if (before >= deadline) break;
          const Outcome outcome = request(client->get(), index, iteration);
          const auto latency = to_ns(Clock::now() - before);
          switch (outcome) {
            case Outcome::Ok:
              totals.ok_ns.push_back(latency);
              break;
            case Outcome::Busy:
              totals.busy_ns.push_back(latency);
              break;
            case Outcome::Error:
              if (totals.errors++ == 0) totals.first_error = modbus_error_text();
              break;
          }
        }
      }
      ended[index] = Clock::now();
    });
  }
  connected.wait();
  start = Clock::now();
  deadline = start + duration;
  go.count_down();
  for (auto& thread : threads) thread.join();

  ClientTotals merged;
  Clock::time_point last = start;
  for (unsigned index = 0; index < clients; ++index) {
    ClientTotals& totals = per_client[index];
    merged.ok_ns.insert(merged.ok_ns.end(), totals.ok_ns.begin(), totals.ok_ns.end());
    merged.busy_ns.insert(merged.busy_ns.end(), totals.busy_ns.begin(), totals.busy_ns.end());
    merged.errors += totals.errors;
    if (merged.first_error.empty()) merged.first_error = totals.first_error;
    last = std::max(last, ended[index]);
  }
  merged.seconds = std::chrono::duration<double>(last - start).count();
  return merged;
}

bool parse_arguments(int argc, char** argv, std::string_view summary, std::initializer_list<Argument> arguments) {
  const auto usage = [&](std::ostream& out) {
    out << argv[0] << ": " << summary << "\n";
    for (const auto& argument : arguments) {
      out << "  --" << argument.name << " N   " << argument.help << " (default " << *argument.value << ")\n";
    }
  };
  for (int index = 1; index < argc; ++index) {
    const std::string_view option = argv[index];
    if (option == "--help" || option == "-h") {
      usage(std::cout);
      return false;
    }
    const auto* found = std::find_if(arguments.begin(), arguments.end(), [&](const Argument& argument) {
      return option.size() > 2 && option.substr(0, 2) == "--" && option.substr(2) == argument.name;
    });
    if (found == arguments.end() || index + 1 >= argc) {
      std::cerr << argv[0] << ": unknown option or missing value: " << option << "\n";
      usage(std::cerr);
      return false;
    }
    char* end = nullptr;
    const double value = std::strtod(argv[++index], &end);
    if (end == argv[index] || *end != '\0' || value < 0) {
      std::cerr << argv[0] << ": " << option << " wants a non-negative number, not '" << argv[index] << "'\n";
      return false;
    }
    *found->value = value;
  }
  return true;
}

void quiet_logs() { spdlog::set_level(spdlog::level::warn); }

void start_precise(simulator::SimulatedBus& bus) {
  const int previous = ::prctl(PR_GET_TIMERSLACK, 0UL, 0UL, 0UL, 0UL);
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
  try {
    bus.start();
  } catch (...) {
    ::prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(previous), 0UL, 0UL, 0UL);
    throw;
  }
  ::prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(previous), 0UL, 0UL, 0UL);
}

}  // namespace sms::bench
