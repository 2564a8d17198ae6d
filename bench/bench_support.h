#pragma once
// What the benchmark programs share: a simulated bus in the bench process, the real
// sms-gateway program as a child process driving it and libmodbus clients (both the tests'
// own, tests/support), client threads, latency summaries and the `name value unit` output lines.
//
// Benchmarks print figures; they assert nothing about time. They talk to 127.0.0.1 only,
// run for a bounded time and stop by themselves. A setup failure (gateway missing, port not
// answering) is an error with what to do, and a non-zero exit.
#include <sys/types.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "simulator/simulated_bus.h"
#include "tests/support/modbus_client.h"
#include "tests/support/processes.h"

namespace sms::bench {

using Clock = std::chrono::steady_clock;

// --- output ----------------------------------------------------------------------------------

// One figure: `name value unit`. Names are dotted paths without spaces.
void print_figure(std::string_view name, double value, std::string_view unit);
// Context for a human reader: `# text`.
void print_note(std::string_view text);

// --- latency ---------------------------------------------------------------------------------

struct LatencySummary {
  std::size_t count = 0;
  double p50_us = 0;
  double p99_us = 0;
  double max_us = 0;
};
// Sorts `samples_ns` in place.
LatencySummary summarize(std::vector<std::uint32_t>& samples_ns);
// `name.p50`, `name.p99` and (with `with_max`) `name.max`, in µs or in ms.
enum class LatencyUnit : std::uint8_t { Us, Ms };
void print_latency(const std::string& name, const LatencySummary& summary, LatencyUnit unit = LatencyUnit::Us,
                   bool with_max = true);
std::uint32_t to_ns(Clock::duration duration);

// --- the bus and its wire time (docs/PROTOCOL.md §5) -----------------------------------------------------

inline constexpr std::uint32_t kBaud = 1'000'000;
inline constexpr unsigned kBitsPerCharacter = 10;  // 8N1
// The sts feedback block the poll cycle reads and FC04 serves: present position .. present
// current (modbus_map::default_poll_block(sts)).
inline constexpr std::uint16_t kFeedbackAddress = 56;
inline constexpr std::uint16_t kFeedbackCount = 15;
inline constexpr std::uint16_t kReturnDelayAddress = 7;  // sts: x 2 us
inline constexpr double kReturnDelayUsPerUnit = 2.0;
// The fastest an sts servo answers: "values below 50 act as 50" (100 us; wiki memory-sts address
// 7, docs/DECISIONS.md "Vendor fidelity"), as the simulator models it. The benchmarks set this
// and count it in their wire models, so "0" never hides 100 us per transaction.
inline constexpr std::uint8_t kStsFastestReturnDelay = 50;
inline constexpr double kStsFastestReturnDelayUs = kStsFastestReturnDelay * kReturnDelayUsPerUnit;

double wire_us(std::size_t bytes, std::uint32_t baud = kBaud);

// `count` sts servos, IDs 1..count, feetech at 1 Mbaud, wire timing on.
simulator::BusOptions sts_bus(unsigned count);
// `count` SMSMB servos (Modbus-RTU firmware), IDs 1..count, at `baud`, wire timing on.
simulator::BusOptions smsmb_bus(unsigned count, std::uint32_t baud);
// Writes the return delay (sts address 7, in 2 us units) of servos 1..count.
void set_return_delay(simulator::SimulatedBus& bus, unsigned count, std::uint8_t units);

// --- the gateway as a child process (tests/support/processes.h) ------------------------------

using test::GatewayProcess;
using test::ModbusClient;

struct GatewaySetup {
  std::string device;   // the simulated bus's pty
  unsigned servos = 6;  // sts IDs 1..servos = units 1..servos
  std::chrono::milliseconds poll_period{20};
  std::chrono::milliseconds probe_period{1000};
  std::size_t max_connections = 200;
  std::size_t request_queue_depth = 64;
  std::chrono::milliseconds response_timeout{20};
  unsigned retries = 2;
  // The bus's watchdog (docs/PLC_GUIDE.md "Safety", feed any_write); empty: none.
  std::optional<std::chrono::milliseconds> watchdog;
  // A modbus-rtu bus of smsmb servos at this rate instead of feetech/sts at kBaud, with this
  // frame_gap (config/README.md); 0: feetech.
  std::uint32_t modbus_rtu_baud = 0;
  std::string frame_gap = "spec";
  std::string extra_yaml;  // appended to the configuration (e.g. an mqtt section)
};

// The YAML configuration for `setup` (the listen address is the process's: 127.0.0.1:0).
std::string gateway_yaml(const GatewaySetup& setup);

using test::free_port;

// build/bin/sms-gateway beside this program, or $SMS_GATEWAY.
std::string gateway_program();

// The gateway of the benchmarks: gateway_program() on `setup`'s configuration (in a directory of
// its own, removed with it), logging at info (events only: nothing per request). Stopped with
// SIGTERM by stop(), killed when destroyed while running.
class BenchGateway {
 public:
  explicit BenchGateway(const GatewaySetup& setup);
  // Waits until the gateway unit says the bus is up with `online` servos online and a poll cycle
  // has finished. Throws std::runtime_error (with the gateway's output) when it does not come.
  void wait_ready(unsigned online);
  std::uint16_t port() const { return process_.port(); }
  pid_t pid() const { return process_.pid(); }
  // Graceful stop; returns the exit status (0 expected).
  int stop() { return process_.stop(); }

 private:
  test::TempDir directory_;
  GatewayProcess process_;
};

// Resident set size of a process (VmRSS in /proc/PID/status), KiB; nullopt when gone.
std::optional<std::uint64_t> rss_kib(pid_t pid);
// Open file descriptors of a process (/proc/PID/fd entries).
std::optional<std::uint64_t> open_fds(pid_t pid);

// --- libmodbus clients -----------------------------------------------------------------------

// 32-bit counter from two registers, high word first (docs/PLC_GUIDE.md).
inline std::uint32_t u32(std::uint16_t high, std::uint16_t low) { return (std::uint32_t{high} << 16) | low; }

// Gateway unit (255) input registers of bus 0 (docs/PLC_GUIDE.md "The gateway unit").
struct BusFacts {
  std::uint16_t state = 0;
  std::uint16_t last_poll_cycle_us = 0;
  std::uint16_t servos_online = 0;
  std::uint32_t frames_ok = 0;
  std::uint32_t timeouts = 0;
  std::uint32_t checksum_errors = 0;
};
inline constexpr int kGatewayUnit = 255;
BusFacts read_bus_facts(ModbusClient& client);  // sets the client's unit to 255

// Servo unit facts, input registers 1000-1007.
struct ServoFacts {
  bool online = false;
  std::uint16_t cache_age_ms = 0;
  std::uint32_t replies_ok = 0;
  std::uint32_t timeouts = 0;
};
ServoFacts read_servo_facts(ModbusClient& client, int unit);  // sets the client's unit

// What one request of a client loop came to.
enum class Outcome : std::uint8_t { Ok, Busy, Error };

struct ClientTotals {
  std::vector<std::uint32_t> ok_ns;    // latency of each answered request
  std::vector<std::uint32_t> busy_ns;  // latency of each exception 0x06 answer
  std::uint64_t errors = 0;            // any other failure
  std::string first_error;
  double seconds = 0;  // from the common start to the last client's end
};

// Runs `clients` threads, each with its own connection to `unit`, all starting together and
// each calling `request(context, client_index, iteration)` back to back until `duration`
// has passed. `nice` > 0 lowers the client threads' priority (setpriority per thread), so a
// flood of clients cannot starve the simulated servos and the gateway of CPU on a small
// machine: on a real bus the servos are other hardware.
using RequestFn = std::function<Outcome(modbus_t*, unsigned client, std::uint64_t iteration)>;
ClientTotals run_clients(std::uint16_t port, int unit, unsigned clients, std::chrono::milliseconds duration,
                         const RequestFn& request, int nice = 0);

// Classifies the result of a libmodbus call (rc < 0: errno tells).
Outcome outcome_of(int rc, int expected);
std::string modbus_error_text();

// Command-line numbers: `--name value` pairs after argv[0]; unknown options are an error.
struct Argument {
  std::string_view name;
  double* value;
  std::string_view help;
};
// nullopt: run with these values; else the program's exit status, the usage printed: 0 after
// --help (on standard output), 2 for a wrong command line (on standard error).
std::optional<int> parse_arguments(int argc, char** argv, std::string_view summary,
                                   std::initializer_list<Argument> arguments);

// spdlog level of the in-process simulator: warnings only.
void quiet_logs();
// Starts the simulated bus with its thread on 1 ns timer slack: with Linux's default 50 us a
// simulated reply leaves up to 50 us after its wire time. This thread's slack (inherited by
// client threads and by the gateway child process) is left as it was.
void start_precise(simulator::SimulatedBus& bus);

}  // namespace sms::bench
