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

std::string gateway_yaml(const GatewaySetup& setup) {
  std::ostringstream yaml;
  yaml << "# written by the sms-gateway benchmarks\n"
       << "modbus_tcp:\n"
       << "  listen: 127.0.0.1:0\n"
       << "  max_connections: " << setup.max_connections << "\n"
       << "  idle_timeout_s: 0\n"
       << "  request_queue_depth: " << setup.request_queue_depth << "\n"
       << "buses:\n"
       << "  - name: bench\n"
       << "    device: \"" << setup.device << "\"\n"
       << "    protocol: " << (setup.modbus_rtu_baud != 0 ? "modbus-rtu" : "feetech") << "\n"
       << "    baud: " << (setup.modbus_rtu_baud != 0 ? setup.modbus_rtu_baud : kBaud) << "\n"
       << "    poll_period_ms: " << setup.poll_period.count() << "\n"
       << "    offline_probe_period_ms: " << setup.probe_period.count() << "\n"
       << "    response_timeout_ms: " << setup.response_timeout.count() << "\n"
       << "    retries: " << setup.retries << "\n";
  if (setup.watchdog) yaml << "    watchdog: {timeout_ms: " << setup.watchdog->count() << ", feed: any_write}\n";
  if (setup.modbus_rtu_baud != 0) yaml << "    frame_gap: " << setup.frame_gap << "\n";
  yaml << "servos:\n";
  const char* table = setup.modbus_rtu_baud != 0 ? "smsmb" : "sts";
  for (unsigned id = 1; id <= setup.servos; ++id)
    yaml << "  - {bus: bench, id: " << id << ", table: " << table << "}\n";
  yaml << setup.extra_yaml;
  return yaml.str();
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

BenchGateway::BenchGateway(const GatewaySetup& setup)
    : process_(GatewayProcess::with_config(directory_, gateway_yaml(setup), 1, {"--log-level", "info"},
                                           gateway_program())) {}

void BenchGateway::wait_ready(unsigned online) {
  std::string last_state = "no answer yet";
  const auto ready = [&] {
    try {
      ModbusClient client(port(), kGatewayUnit, 500ms);
      const BusFacts facts = read_bus_facts(client);
      last_state = "bus state " + std::to_string(facts.state) + ", " + std::to_string(facts.servos_online) +
                   " servos online, last poll cycle " + std::to_string(facts.last_poll_cycle_us) + " us";
      return facts.state == 1 && facts.servos_online == online && facts.last_poll_cycle_us > 0;
    } catch (const std::exception& error) {
      last_state = error.what();
      return false;
    }
  };
  if (!test::poll_until(ready)) {
    throw std::runtime_error(
        "sms-gateway on port " + std::to_string(port()) + ": " +
        test::await_failure("its bus up with " + std::to_string(online) + " servos online and a poll cycle done",
                            test::kAwaitTimeout) +
        " (last seen: " + last_state + "); its output:\n" + process_.process().output());
  }
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

BusFacts read_bus_facts(ModbusClient& client) {
  client.set_unit(kGatewayUnit);
  const auto r = client.read_input(100, 10).or_throw("FC04 unit 255, 100+10 (bus 0's facts)");  // 100 + 20 * 0
  return BusFacts{r[0], r[2], r[3], u32(r[4], r[5]), u32(r[6], r[7]), u32(r[8], r[9])};
}

ServoFacts read_servo_facts(ModbusClient& client, int unit) {
  client.set_unit(unit);
  const auto r = client.read_input(1000, 8).or_throw("FC04 unit " + std::to_string(unit) + ", 1000+8 (servo facts)");
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
          const Outcome outcome = request(client->context(), index, iteration);
          const auto latency = to_ns(Clock::now() - before);
          switch (outcome) {
            case Outcome::Ok: totals.ok_ns.push_back(latency); break;
            case Outcome::Busy: totals.busy_ns.push_back(latency); break;
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

std::optional<int> parse_arguments(int argc, char** argv, std::string_view summary,
                                   std::initializer_list<Argument> arguments) {
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
      return 0;
    }
    const auto* found = std::find_if(arguments.begin(), arguments.end(), [&](const Argument& argument) {
      return option.size() > 2 && option.substr(0, 2) == "--" && option.substr(2) == argument.name;
    });
    if (found == arguments.end() || index + 1 >= argc) {
      std::cerr << argv[0] << ": unknown option or missing value: " << option << "\n";
      usage(std::cerr);
      return 2;
    }
    char* end = nullptr;
    const double value = std::strtod(argv[++index], &end);
    if (end == argv[index] || *end != '\0' || value < 0) {
      std::cerr << argv[0] << ": " << option << " wants a non-negative number, not '" << argv[index] << "'\n";
      return 2;
    }
    *found->value = value;
  }
  return std::nullopt;
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
