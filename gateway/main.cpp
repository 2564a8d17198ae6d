// sms-gateway: Modbus TCP for serial-bus servos (docs/PLC_GUIDE.md is the contract).
//
//   sms-gateway --config /etc/sms-gateway/gateway.yaml
//   sms-gateway --simulate                   # 6 simulated sts servos, units 1-6, 127.0.0.1:5020
//   sms-gateway --check-config gateway.yaml
//
// Integrator tools (scan, set-id, set-baud, calibrate-middle, factory-reset, dump, tags) and the transparent
// forwarder come as subcommands (gateway/tools/tool_cli.h); without a subcommand the gateway runs.
#include <signal.h>

#include <chrono>
#include <cstdio>
#include <iostream>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "config/env.h"
#include "config/load.h"
#include "config/secret_files.h"
#include "gateway/console/console_access.h"
#include "gateway/gateway.h"
#include "gateway/modbus_tcp/tls.h"
#include "gateway/mqtt/sparkplug_node.h"
#include "gateway/observability/logging.h"
#include "gateway/tools/tool_cli.h"
#include "gateway/units/state_file.h"
#include "process/stop_signals.h"
#include "simulator/simulated_bus.h"

namespace {

using sms::config::Config;
using sms::config::LogLevel;

constexpr int kExitOk = 0;
constexpr int kExitRuntimeError = 1;
constexpr int kExitConfigError = 2;

struct Options {
  std::string config_file;
  bool simulate = false;
  std::string listen;
  std::string metrics;
  std::string log_level;
  std::string check_config_file;
  bool version = false;
  std::vector<std::string> rtu_slaves;  // --rtu-slave DEVICE[:BAUD[:PARITY]], each an upstream port
  std::string console;                  // --console HOST:PORT: the browser console (docs/CONSOLE.md)
};

// --simulate serves the browser console here unless --console says otherwise.
const sms::config::HostPort kSimulateConsole{"127.0.0.1", 8080};

// --log-level wins over the configuration's logging.level.
std::optional<LogLevel> log_level_from(const std::string& name) {
  for (const LogLevel level : {LogLevel::Trace, LogLevel::Debug, LogLevel::Info, LogLevel::Warn, LogLevel::Error,
                               LogLevel::Critical, LogLevel::Off}) {
    if (sms::config::to_string(level) == name) return level;
  }
  return std::nullopt;
}

std::string summary(const Config& config) {
  std::string listeners;
  if (config.modbus_tcp.plain) listeners = "Modbus TCP on " + config.modbus_tcp.listen.to_string();
  if (config.modbus_tcp.tls) {
    listeners += (listeners.empty() ? "" : ", ") + std::string("Modbus/TCP Security on ") +
                 config.modbus_tcp.tls->listen.to_string();
  }
  return std::to_string(config.buses.size()) + " bus(es), " + std::to_string(config.servos.size()) + " servo(s), " +
         std::to_string(config.sync_groups.size()) + " sync group(s); " + listeners + ", gateway unit " +
         std::to_string(config.modbus_tcp.gateway_unit_id) +
         (config.mqtt ? "; Sparkplug B node " + config.mqtt->group_id + "/" + config.mqtt->edge_node_id +
                            " on broker " + config.mqtt->broker.to_string()
                      : std::string()) +
         (config.modbus_rtu_slave.empty()
              ? std::string()
              : "; " + std::to_string(config.modbus_rtu_slave.size()) + " upstream Modbus RTU port(s)");
}

// What a bus promises a stop (docs/SAFETY.md "How long a stop can take"): its worst transaction,
// and with a watchdog the latest its stop frames leave after the last feed.
std::string bus_bounds(const sms::config::BusConfig& bus) {
  const auto worst = sms::config::worst_transaction(bus);
  std::string text = "bus " + bus.name + ": worst transaction " + std::to_string(worst.count()) + " ms (" +
                     std::to_string(1 + bus.retries) + " attempts of a fence read and the request, " +
                     std::to_string(bus.response_timeout.count()) + " ms response timeout each)";
  if (bus.watchdog) {
    text += "; a watchdog stop leaves at most " + std::to_string((bus.watchdog->timeout + worst).count()) +
            " ms after the last feed (timeout_ms " + std::to_string(bus.watchdog->timeout.count()) +
            " + that transaction)";
  } else {
    text += "; no watchdog";
  }
  if (const auto gap = sms::config::d55d_instruction_gap(bus)) {
    text += "; an online d55d motor hears an instruction at least every " + std::to_string(gap->count()) +
            " ms, an offline one is probed every " + std::to_string(sms::config::effective_probe_period(bus).count()) +
            " ms (their heartbeat stops them after " + std::to_string(sms::config::kD55dHeartbeat.count()) + " ms)";
  }
  return text;
}

// A d55d bus whose motors can go longer without an instruction than their heartbeat allows: one
// may stop by itself while another servo does not answer (docs/PLC_GUIDE.md "d55d heartbeat").
std::vector<std::string> heartbeat_warnings(const Config& config) {
  std::vector<std::string> warnings;
  for (const auto& bus : config.buses) {
    const auto gap = sms::config::d55d_instruction_gap(bus);
    if (!gap || *gap < sms::config::kD55dHeartbeat) continue;
    warnings.push_back("bus " + bus.name + ": a d55d motor can go " + std::to_string(gap->count()) +
                       " ms without an instruction (poll_period_ms, then a transaction to another servo of " +
                       std::to_string(sms::config::worst_transaction(bus).count()) +
                       " ms at most): its 500 ms heartbeat can stop it while another motor does not answer; lower "
                       "response_timeout_ms or retries (or poll_period_ms) until the gap is under 500 ms");
  }
  return warnings;
}

// --rtu-slave options appended to config.modbus_rtu_slave; false after printing why one cannot be.
bool add_rtu_slave_options(const std::vector<std::string>& texts, Config& config) {
  for (const auto& text : texts) {
    auto port = sms::config::parse_rtu_slave_option(text);
    if (!port) {
      std::cerr << "sms-gateway: --rtu-slave " << port.error() << "\n";
      return false;
    }
    if (const auto conflict = sms::config::rtu_slave_conflict(config, *port)) {
      std::cerr << "sms-gateway: --rtu-slave " << text << ": " << *conflict << "\n";
      return false;
    }
    config.modbus_rtu_slave.push_back(std::move(*port));
  }
  return true;
}

// SMS_GATEWAY_* variables over the configuration (config/env.h); false after printing why not.
bool apply_environment(Config& config, std::vector<std::string>& applied) {
  auto result = sms::config::apply_environment(config);
  if (!result) {
    std::cerr << "sms-gateway: environment: " << result.error() << "\n";
    return false;
  }
  applied = std::move(*result);
  return true;
}

std::string joined(const std::vector<std::string>& names) {
  std::string text;
  for (const auto& name : names) text += (text.empty() ? "" : ", ") + name;
  return text;
}

// What the gateway warns about at every start with this configuration, which --check-config says
// too: files with secrets that every user may read, password logins over plain HTTP.
std::vector<std::string> start_warnings(const Config& config, const std::string& config_path) {
  std::vector<std::string> warnings = sms::config::secret_file_warnings(config, config_path);
  for (auto& warning : heartbeat_warnings(config)) warnings.push_back(std::move(warning));
  if (const auto& console = config.console; console && console->insecure_http && !console->users.empty() &&
                                            !sms::config::is_loopback_host(console->listen.host)) {
    warnings.push_back("console: passwords of console.users cross the network in clear: http://" +
                       console->listen.to_string() +
                       " is plain HTTP on a non-loopback address (console.insecure_http: true); give the console a "
                       "certificate and key (console.certificate, console.key) and remove insecure_http");
  }
  return warnings;
}

// Checks the file and the environment variables the gateway would apply over it.
int check_config(const std::string& path) {
  auto config = sms::config::load_config_file(path);
  if (!config) {
    std::cerr << config.error().to_string() << "\n";
    return kExitConfigError;
  }
  std::vector<std::string> applied;
  if (!apply_environment(*config, applied)) return kExitConfigError;
  if (const auto& tls = config->modbus_tcp.tls) {
    // The files as the gateway will load them: a missing key or a key of another certificate
    // fails here (ExecStartPre), not at start.
    try {
      sms::gateway::make_tls_context(*tls);
    } catch (const std::exception& error) {
      std::cerr << path << ": " << error.what() << "\n";
      return kExitConfigError;
    }
  }
  if (const auto& mqtt = config->mqtt) {
    try {
      sms::gateway::read_mqtt_files(*mqtt);
    } catch (const std::exception& error) {
      std::cerr << path << ": " << error.what() << "\n";
      return kExitConfigError;
    }
  }
  if (const std::string dir = sms::config::effective_state_dir(*config); !dir.empty()) {
    if (const std::string problem = sms::gateway::check_state_dir(dir); !problem.empty()) {
      std::cerr << path << ": " << problem << "\n";
      return kExitConfigError;
    }
  }
  const auto warnings = start_warnings(*config, path);
  for (const auto& warning : warnings) std::cerr << path << ": warning: " << warning << "\n";
  std::cout << path << ": OK"
            << (warnings.empty() ? std::string() : " (" + std::to_string(warnings.size()) + " warning(s) above)")
            << ": " << summary(*config);
  if (!applied.empty()) std::cout << " (with " << joined(applied) << " from the environment)";
  std::cout << "\n";
  for (const auto& bus : config->buses) std::cout << path << ": " << bus_bounds(bus) << "\n";
  return kExitOk;
}

std::string environment_help() {
  std::string text;
  for (const auto& variable : sms::config::environment_variables()) {
    text += "  " + std::string(variable.name) + "=" + std::string(variable.form) + "  (" +
            std::string(variable.setting) + ")\n";
  }
  return text;
}

// A HOST:PORT option into `address` (left empty when the option was not given); false after
// printing why the text is not an address.
bool address_option(std::string_view option, const std::string& text, std::optional<sms::config::HostPort>& address) {
  if (text.empty()) return true;
  auto parsed = sms::config::parse_host_port(text);
  if (!parsed) {
    std::cerr << "sms-gateway: " << option << " " << text << ": " << parsed.error() << "\n";
    return false;
  }
  address = *parsed;
  return true;
}

int run_gateway(const Options& options) {
  // SIGINT/SIGTERM stop, SIGHUP reloads the TLS files; blocked before any thread starts.
  const sms::process::StopSignals stop_signals({SIGHUP});

  std::optional<sms::config::HostPort> listen;
  std::optional<sms::config::HostPort> metrics;
  std::optional<sms::config::HostPort> console;
  if (!address_option("--listen", options.listen, listen) || !address_option("--metrics", options.metrics, metrics) ||
      !address_option("--console", options.console, console)) {
    return kExitConfigError;
  }

  std::optional<sms::simulator::SimulatedBus> simulated_bus;
  Config config;
  if (options.simulate) {
    try {
      simulated_bus.emplace(sms::simulator::default_bus_options());
      simulated_bus->start();
    } catch (const std::exception& error) {
      std::cerr << "sms-gateway: cannot start the simulated bus: " << error.what() << "\n";
      return kExitRuntimeError;
    }
    config = sms::gateway::simulated_config(simulated_bus->slave_path(), sms::config::HostPort{"127.0.0.1", 5020});
  } else {
    auto loaded = sms::config::load_config_file(options.config_file);
    if (!loaded) {
      std::cerr << loaded.error().to_string() << "\n";
      return kExitConfigError;
    }
    config = std::move(*loaded);
  }
  // Precedence: command line, then environment, then the file (or the --simulate default).
  std::vector<std::string> from_environment;
  if (!apply_environment(config, from_environment)) return kExitConfigError;
  if (listen) config.modbus_tcp.listen = *listen;
  if (metrics) config.logging.metrics_listen = *metrics;
  if (!options.log_level.empty()) config.logging.level = *log_level_from(options.log_level);
  if (!add_rtu_slave_options(options.rtu_slaves, config)) return kExitConfigError;
  if (options.simulate) {
    // The demo's console: simulated servos on this machine only, so its local user may do
    // everything (the jog panel, commissioning); a configured console keeps its own rules.
    if (!config.console) config.console.emplace();
    config.console->listen = console.value_or(kSimulateConsole);
    config.console->local_user_has_every_right = config.console->users.empty() && !config.console->tls;
    config.console->any_port_if_taken = !console.has_value();
    if (config.console->local_user_has_every_right && !sms::config::is_loopback_host(config.console->listen.host)) {
      std::cerr << "sms-gateway: --console " << config.console->listen.to_string()
                << ": --simulate serves the console on a loopback address only (its local user has every right)\n";
      return kExitConfigError;
    }
  } else if (console) {
    if (!config.console) config.console.emplace();
    config.console->listen = *console;
    if (const auto problem = sms::config::console_listen_problem(*config.console)) {
      std::cerr << "sms-gateway: --console " << *problem << " (docs/CONSOLE.md \"Access\")\n";
      return kExitConfigError;
    }
  }
  sms::gateway::setup_logging(config.logging);
  if (!from_environment.empty()) spdlog::info("from the environment: {}", joined(from_environment));

  if (options.simulate) {
    spdlog::info("simulated bus: 6 sts servos (IDs 1-6 = units 1-6), feetech at 1000000 bit/s on {}",
                 simulated_bus->slave_path());
  } else {
    spdlog::info("configuration {}: {}", options.config_file, summary(config));
  }
  // Password hashes and private keys readable by every user of the machine: said at every start.
  for (const auto& warning : sms::config::secret_file_warnings(config, options.simulate ? "" : options.config_file)) {
    spdlog::warn("{}", warning);
  }
  for (const auto& warning : heartbeat_warnings(config)) spdlog::warn("{}", warning);

  // The e-stop latch is kept there: a gateway that could not keep it does not start.
  if (const std::string dir = sms::config::effective_state_dir(config); !dir.empty()) {
    if (const std::string problem = sms::gateway::check_state_dir(dir); !problem.empty()) {
      spdlog::critical("{}", problem);
      return kExitConfigError;
    }
  }
  try {
    sms::gateway::Gateway gateway(std::move(config));
    gateway.start();
    if (!gateway.console_url().empty()) {
      spdlog::info("browser console: {}", gateway.console_url());
      // The demo says where to click in plain words too; with JSON logs every line stays JSON.
      if (options.simulate && gateway.config().logging.format == sms::config::LogFormat::Plain) {
        std::cout << "Browser console: " << gateway.console_url() << std::endl;
      }
    }
    int signal_number = 0;
    while ((signal_number = stop_signals.wait()) == SIGHUP) {
      spdlog::info("SIGHUP received: reloading the Modbus/TCP Security certificate, key and CA");
      gateway.reload_tls();
    }
    spdlog::info("{} received: finishing the requests in flight, then stopping",
                 sms::process::StopSignals::name(signal_number));
    gateway.stop();
  } catch (const std::exception& error) {
    spdlog::critical("{}", error.what());
    return kExitRuntimeError;
  }
  if (simulated_bus) simulated_bus->stop();
  spdlog::info("stopped");
  return kExitOk;
}

// What `argument`, not understood by the command line, is not.
std::string unknown_argument(const CLI::App& app, const std::string& argument) {
  if (argument.starts_with('-')) return "no option " + argument + " (sms-gateway --help lists them)";
  std::string commands;
  for (const CLI::App* command : app.get_subcommands([](const CLI::App*) { return true; })) {
    commands += (commands.empty() ? "" : ", ") + command->get_name();
  }
  return "no command " + argument + "; the commands are " + commands;
}

}  // namespace

static int run_command_line(int argc, char** argv) {
  CLI::App app{
      "sms-gateway: Modbus TCP gateway for Feetech (FF FF), D5 5D and SMSMB serial-bus servos.\n"
      "Runs the gateway from a configuration file, or on a built-in simulated bus (--simulate)."};
  Options options;
  auto* config_option = app.add_option("--config", options.config_file, "YAML configuration file to run");
  auto* simulate_option =
      app.add_flag("--simulate", options.simulate,
                   "Run on a built-in simulated bus: 6 sts servos (IDs 1-6 = units 1-6), feetech at 1000000 "
                   "baud; listens on 127.0.0.1:5020 unless --listen says otherwise");
  config_option->excludes(simulate_option);
  app.add_option("--listen", options.listen, "HOST:PORT to serve Modbus TCP on (overrides modbus_tcp.listen)");
  app.add_option("--metrics", options.metrics,
                 "HOST:PORT to serve /metrics (Prometheus) and /healthz on (overrides logging.metrics_listen)");
  app.add_option("--log-level", options.log_level, "trace, debug, info, warn, error, critical or off")
      ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error", "critical", "off"}));
  app.add_option("--rtu-slave", options.rtu_slaves,
                 "DEVICE[:BAUD[:PARITY]]: also serve Modbus RTU masters (PLCs, HMI panels) on this serial device as "
                 "a slave, every unit, role operate (baud 19200 and parity even unless given; none, even or odd). "
                 "May be given more than once; adds to modbus_rtu_slave")
      ->type_name("DEVICE[:BAUD[:PARITY]]");
  app.add_option("--console", options.console,
                 "HOST:PORT to serve the browser console on (overrides console.listen; --simulate: 127.0.0.1:8080)")
      ->type_name("HOST:PORT");
  auto* check_option = app.add_option("--check-config", options.check_config_file,
                                      "Validate a configuration file and exit (0 valid, 2 invalid)");
  check_option->excludes(simulate_option);
  app.add_flag("--version", options.version, "Print the version and exit");
  app.footer("Environment (for containers; the command line wins over it, it wins over the file):\n" +
             environment_help());
  // Subcommands run inside parse() and end it with their exit status; without one, the gateway runs.
  sms::gateway::add_tool_commands(app);
  // A password hash for console.users (docs/CONSOLE.md): the password on standard input.
  app.add_subcommand("hash-password",
                     "Read a password from standard input (first line) and print its hash for console.users "
                     "password_hash (libsodium crypto_pwhash_str, Argon2id)")
      ->callback([] {
        std::string password;
        std::getline(std::cin, password);
        if (!password.empty() && password.back() == '\r') password.pop_back();
        if (password.empty()) {
          std::cerr << "sms-gateway hash-password: no password on standard input\n";
          throw CLI::RuntimeError(kExitConfigError);
        }
        std::cout << sms::gateway::console::hash_password(password) << "\n";
        throw CLI::RuntimeError(kExitOk);
      });
  app.require_subcommand(0, 1);

  try {
    app.parse(argc, argv);
  } catch (const CLI::RuntimeError& finished) {
    return finished.get_exit_code();  // a tool subcommand ended with its own status
  } catch (const CLI::CallForHelp& help) {
    // `sms-gateway NAME --help` where NAME is not a command: CLI11 answers --help before it looks
    // at what it did not understand, and would print the general help with status 0.
    if (const auto unknown = app.remaining(true); !unknown.empty()) {
      std::cerr << "sms-gateway: " << unknown_argument(app, unknown.front()) << "\n";
      return kExitConfigError;
    }
    return app.exit(help);
  } catch (const CLI::ParseError& error) {
    // CLI11 prints the message; its own codes (105, 109, 114, ...) become the documented
    // command-line error status 2 (README "Command line"); --help stays 0.
    return app.exit(error) == kExitOk ? kExitOk : kExitConfigError;
  }

  if (options.version) {
    std::cout << "sms-gateway " << SMS_GATEWAY_VERSION << "\n";
    return kExitOk;
  }
  if (!options.check_config_file.empty()) return check_config(options.check_config_file);
  if (options.config_file.empty() && !options.simulate) {
    std::cerr << "sms-gateway: say what to run: --config FILE (a configuration), or --simulate (the built-in "
                 "simulated bus). See --help.\n";
    return kExitConfigError;
  }
  return run_gateway(options);
}

int main(int argc, char** argv) {
  // Whatever escapes is a bug: say so and exit with the runtime-error status, not an abort
  // (stdio here: it cannot throw).
  try {
    return run_command_line(argc, argv);
  } catch (const std::exception& error) {
    std::fprintf(stderr, "sms-gateway: internal error: %s\n", error.what());
    return kExitRuntimeError;
  } catch (...) {
    std::fputs("sms-gateway: internal error: an exception of unknown type\n", stderr);
    return kExitRuntimeError;
  }
}
