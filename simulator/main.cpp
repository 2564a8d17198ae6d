// sms-sim: a whole simulated servo bus on a pseudo-terminal (or a serial device), for
// developing and testing against servos that are not on the desk. See `sms-sim --help`.

#include <cstdio>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "modbus_map/tables.h"
#include "process/stop_signals.h"
#include "simulator/bus_spec.h"
#include "simulator/control_server.h"
#include "simulator/simulated_bus.h"

namespace {

using namespace sms;
using namespace sms::simulator;

constexpr const char* kDescription = R"(sms-sim: simulated RS-485 servos on a pseudo-terminal.

Prints the pty path (one line, flushed) and answers on it until SIGINT/SIGTERM. A host opens
the path like a serial port; a servo answers only when the host's line speed equals its baud,
so several rates and protocols can share one bus. Tables: sts, sms1 and scs (protocol
feetech, FF FF), d55d (protocol d55d, D5 5D), smsmb (protocol modbus-rtu: FC 03/06/10/11/41, FC 04 ->
exception 0x01). Every instruction of the protocol is simulated, with a motion model behind
the present-value fields.

Wire timing: a reply is written no earlier than request + return delay + reply on the wire at
10 bits a character (--no-timing answers at once).

State file: per servo slot (its place on the command line), the EEPROM that survives a power
cycle: writes made while the lock is open (sts 55 = 0, sms1 48 = 0, scs 48 = 0, smsmb 0x85 = 0
or 128; d55d always) and the BACKUP image. A saved ID or baud wins over the command line.

Examples:
  sms-sim --ids 1-6                                    6 STS servos, feetech, 1 Mbaud
  sms-sim --protocol modbus-rtu --ids 1,3 --baud 115200 --link /tmp/ttySIM0
  sms-sim --servo 1:sts:feetech:1000000 --servo 2:smsmb:modbus-rtu:115200 --servo 3:d55d:d55d:115200
  sms-sim --ids 1-3 --drop 0.1 --late 2:50 --control /tmp/sim.sock

Control socket (--control PATH; one command per line, one reply line each: "ok", data or
"error: ..."):
  offline ID | online ID | drop P | corrupt P | corrupt-next [N] | garble ID on|off | late ID MS |
  error ID BITS | duplicate ID | timing on|off | get ID ADDR COUNT (hex bytes) | set ID ADDR HEX... |
  field ID NAME | motion ID (last goal's start and arrival, steady-clock µs) | list | stats |
  holds (times the machine held the simulator, steady-clock µs) | help
  e.g. `get 3 56 2` -> `18 05`, `set 3 42 00 08`, `error 2 0x04`, `late 2 50`.
  SMSMB addresses are registers; get/set move 2 bytes per register, high byte first.
)";

std::vector<ServoConfig> build_servos(const std::optional<std::string>& protocol_name,
                                      const std::optional<std::string>& table_name, const std::string& ids,
                                      std::optional<std::uint32_t> baud, const std::vector<std::string>& servo_specs,
                                      bool ids_given) {
  std::optional<protocol::BusProtocol> protocol;
  if (protocol_name) {
    protocol = protocol::bus_protocol_from_string(*protocol_name);
    if (!protocol)
      throw CLI::ValidationError("--protocol", "'" + *protocol_name + "': use feetech, d55d or modbus-rtu");
  }
  std::optional<modbus_map::TableId> table;
  if (table_name) {
    table = modbus_map::table_from_name(*table_name);
    if (!table) throw CLI::ValidationError("--table", "'" + *table_name + "': use sts, sms1, scs, d55d or smsmb");
  }
  if (table && protocol && protocol_of(*table) != *protocol) {
    throw CLI::ValidationError("--table", "table " + *table_name + " is spoken over " +
                                              std::string(protocol::to_string(protocol_of(*table))) + ", not " +
                                              *protocol_name);
  }
  const protocol::BusProtocol bus_protocol =
      protocol ? *protocol : (table ? protocol_of(*table) : protocol::BusProtocol::Feetech);
  const modbus_map::TableId bus_table = table ? *table : default_table(bus_protocol);

  std::vector<ServoConfig> servos;
  if (ids_given || servo_specs.empty()) {
    const auto list = parse_id_list(ids);
    if (!list) throw CLI::ValidationError("--ids", list.error());
    for (const std::uint8_t id : *list) {
      servos.push_back(ServoConfig{id, bus_table, bus_protocol, baud.value_or(default_baud(bus_protocol))});
    }
  }
  for (const std::string& spec : servo_specs) {
    const auto servo = parse_servo_spec(spec);
    if (!servo) throw CLI::ValidationError("--servo", servo.error());
    servos.push_back(*servo);
  }
  return servos;
}

}  // namespace

static int run_command_line(int argc, char** argv) {
  CLI::App app{kDescription, "sms-sim"};
  app.get_formatter()->column_width(34);

  std::optional<std::string> protocol_name;
  std::optional<std::string> table_name;
  std::string ids = "1-6";
  std::optional<std::uint32_t> baud;
  std::vector<std::string> servo_specs;
  BusOptions options;
  bool no_timing = false;
  std::string control_path;
  std::optional<double> drop;
  std::optional<double> corrupt;
  std::vector<std::string> late;
  std::vector<std::string> errors;
  std::vector<unsigned> offline;
  std::vector<unsigned> duplicates;
  unsigned reboot_ms = 500;
  bool verbose = false;

  app.add_option("--protocol", protocol_name,
                 "Bus protocol of the --ids servos: feetech, d55d or modbus-rtu "
                 "(default: the table's, else feetech)");
  app.add_option("--table", table_name,
                 "Control table of the --ids servos: sts, sms1, scs, d55d or smsmb "
                 "(default: sts / d55d / smsmb by protocol)");
  auto* ids_option = app.add_option("--ids", ids, "Servo IDs: 1-6, 1,3,7 or 1-3,7")->capture_default_str();
  app.add_option("--baud", baud, "Baud of the --ids servos (default: 1000000 feetech, 115200 d55d and modbus-rtu)");
  app.add_option("--servo", servo_specs,
                 "One more servo, ID:TABLE:PROTOCOL:BAUD (repeatable; PROTOCOL and BAUD may be left out) - "
                 "several rates and protocols may share the bus. Without --ids, only these servos are simulated");
  app.add_option("--link", options.link, "Also make this symlink to the pty (e.g. /tmp/ttySIM0)");
  app.add_option("--device", options.device,
                 "Answer on this serial device instead of a pty (set to the first servo's baud)");
  app.add_flag("--no-timing", no_timing,
               "Answer at once instead of after the wire time (request + return delay + reply, "
               "10 bits a character)");
  app.add_option("--state-file", options.state_file,
                 "Keep EEPROM here across restarts: unlocked EEPROM writes survive (sts lock 55, sms1 48, smsmb 0x85)");
  app.add_option("--control", control_path, "Unix socket for run-time commands (listed above)");
  app.add_option("--drop", drop, "Drop each reply with probability P (0-1)")->check(CLI::Range(0.0, 1.0));
  app.add_option("--corrupt", corrupt, "Flip a byte in each reply with probability P (0-1)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--late", late, "ID:MS - servo ID answers MS milliseconds late (repeatable)");
  app.add_option("--offline", offline, "Servo ID does not answer (repeatable)")->check(CLI::Range(0, 253));
  app.add_option("--error", errors, "ID:BITS - servo ID reports these ERROR/status bits, e.g. 2:0x04 (repeatable)");
  app.add_option("--duplicate", duplicates, "A second servo with this ID answers at the same time (repeatable)")
      ->check(CLI::Range(0, 253));
  app.add_option("--reboot-ms", reboot_ms, "How long a servo stays deaf after REBOOT or Modbus restart")
      ->capture_default_str();
  app.add_option("--seed", options.seed, "Seed for the fault dice (default: random)");
  app.add_flag("-v,--verbose", verbose, "Log every frame received and sent (stderr)");

  try {
    app.parse(argc, argv);
    options.servos = build_servos(protocol_name, table_name, ids, baud, servo_specs, ids_option->count() > 0);
  } catch (const CLI::ParseError& error) {
    // CLI11's own codes (105, 109, 114, ...) become one command-line error status, 2; --help stays 0.
    return app.exit(error) == 0 ? 0 : 2;
  }
  options.timing = !no_timing;
  options.reboot_time = std::chrono::milliseconds(reboot_ms);
  spdlog::set_level(verbose ? spdlog::level::debug : spdlog::level::warn);

  // Blocked before any thread starts, then waited for here.
  const sms::process::StopSignals stop_signals;

  try {
    SimulatedBus bus(options);
    const auto require_servo = [&](std::uint32_t id, const std::string& option) {
      for (const ServoSummary& servo : bus.servos()) {
        if (servo.config.id == id) return static_cast<std::uint8_t>(id);
      }
      throw std::invalid_argument(option + ": no servo has ID " + std::to_string(id));
    };
    for (const unsigned id : duplicates) bus.add_duplicate(require_servo(id, "--duplicate"));
    for (const unsigned id : offline) bus.set_offline(require_servo(id, "--offline"), true);
    if (drop) bus.set_drop_probability(*drop);
    if (corrupt) bus.set_corrupt_probability(*corrupt);
    for (const std::string& entry : late) {
      const auto pair = parse_id_value(entry);
      if (!pair) throw std::invalid_argument("--late " + pair.error() + "; write ID:MS, e.g. 2:50");
      bus.set_reply_delay(require_servo(pair->first, "--late"), std::chrono::milliseconds(pair->second));
    }
    for (const std::string& entry : errors) {
      const auto pair = parse_id_value(entry);
      if (!pair || pair->second > 0xFF) {
        throw std::invalid_argument("--error '" + entry + "': write ID:BITS with BITS 0-255, e.g. 2:0x04");
      }
      bus.set_error_bits(require_servo(pair->first, "--error"), static_cast<std::uint8_t>(pair->second));
    }
    bus.start();
    std::optional<ControlServer> control;
    if (!control_path.empty()) control.emplace(bus, control_path);
    std::cout << bus.slave_path() << std::endl;  // flushed: scripts read this line

    stop_signals.wait();
    control.reset();
    bus.stop();
  } catch (const std::exception& error) {
    std::cerr << "sms-sim: " << error.what() << "\n";
    return 1;
  }
  return 0;
}

int main(int argc, char** argv) {
  // Whatever escapes is a bug: say so and exit with the runtime-error status, not an abort
  // (stdio here: it cannot throw).
  try {
    return run_command_line(argc, argv);
  } catch (const std::exception& error) {
    std::fprintf(stderr, "sms-sim: internal error: %s\n", error.what());
    return 1;
  } catch (...) {
    std::fputs("sms-sim: internal error: an exception of unknown type\n", stderr);
    return 1;
  }
}
