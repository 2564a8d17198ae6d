#include "gateway/tools/tool_cli.h"

#include <algorithm>
#include <cstring>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "config/load.h"
#include "gateway/service/unit_catalog.h"
#include "gateway/tools/tag_list.h"
#include "gateway/tools/tool_scan.h"
#include "gateway/tools/tool_servo.h"
#include "gateway/units/passthrough.h"
#include "modbus_map/baud_tables.h"
#include "modbus_map/tables.h"
#include "process/stop_signals.h"

namespace sms::gateway {
namespace {

constexpr int kExitOk = 0;
constexpr int kExitFailed = 1;
constexpr int kExitUsage = 2;

[[noreturn]] void finish(int status) { throw CLI::RuntimeError(status); }

[[noreturn]] void fail(std::string_view command, const std::string& message, int status = kExitFailed) {
  std::cerr << "sms-gateway " << command << ": " << message << "\n";
  finish(status);
}

struct ParityName {
  std::string_view name;
  config::Parity parity;
};
constexpr ParityName kParityNames[] = {
    {"none", config::Parity::None}, {"N", config::Parity::None},  {"even", config::Parity::Even},
    {"E", config::Parity::Even},    {"odd", config::Parity::Odd}, {"O", config::Parity::Odd},
};

struct RtsName {
  std::string_view name;
  config::RtsMode rts;
};
constexpr RtsName kRtsNames[] = {
    {"none", config::RtsMode::None}, {"up", config::RtsMode::Up}, {"down", config::RtsMode::Down}};

config::Parity parity_from(const std::string& name) {
  for (const auto& entry : kParityNames) {
    if (entry.name == name) return entry.parity;
  }
  return config::Parity::None;  // CLI::IsMember has refused anything else
}

char parity_letter(config::Parity parity) {
  for (const auto& entry : kParityNames) {
    if (entry.parity == parity && entry.name.size() == 1) return entry.name[0];
  }
  return 'N';
}

config::RtsMode rts_from(const std::string& name) {
  for (const auto& entry : kRtsNames) {
    if (entry.name == name) return entry.rts;
  }
  return config::RtsMode::None;
}

// "1-10,20,30-32" -> IDs; the error says what is wrong.
Expected<std::vector<std::uint8_t>> parse_ids(const std::string& text) {
  std::vector<std::uint8_t> ids;
  std::size_t start = 0;
  while (start <= text.size()) {
    const std::size_t comma = text.find(',', start);
    const std::string item = text.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    const std::size_t dash = item.find('-');
    unsigned first = 0;
    unsigned last = 0;
    try {
      std::size_t used = 0;
      // 64 bits on every architecture, capped before the cast: a huge number is refused as out of
      // range, never truncated to a small ID (stoul: 32 bits on armhf, 64 on amd64 and arm64).
      const auto id_of = [&](const std::string& digits) {
        return static_cast<unsigned>(std::min<unsigned long long>(std::stoull(digits, &used), 254));
      };
      first = id_of(item.substr(0, dash));
      if (used != item.substr(0, dash).size()) throw std::invalid_argument(item);
      last = first;
      if (dash != std::string::npos) {
        last = id_of(item.substr(dash + 1));
        if (used != item.size() - dash - 1) throw std::invalid_argument(item);
      }
    } catch (const std::exception&) {
      return unexpected("'" + item + "' is not an ID or a range such as 1-10");
    }
    if (last < first || last > 253) return unexpected("'" + item + "': IDs are 0-253, ranges low-high");
    for (unsigned id = first; id <= last; ++id) ids.push_back(static_cast<std::uint8_t>(id));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return ids;
}

std::vector<std::string> names_of_protocols() { return {"feetech", "d55d", "modbus-rtu"}; }

// The options every servo tool shares.
struct LineArgs {
  std::string device;
  std::string protocol;
  std::uint32_t baud = 0;
  std::string parity = "none";
  unsigned stop_bits = 1;
  // The scan asks hundreds of IDs and keeps it short; a tool changing one servo asks a few
  // times and can afford to wait for a slow adapter.
  unsigned latency_ms = 10;
  std::string table;
  unsigned id = 1;
  bool force = false;
};

void add_line_options(CLI::App& command, LineArgs& args, bool baud_required) {
  command.add_option("--device", args.device, "Serial device of the bus (/dev/ttyUSB0, /dev/serial/by-id/...)")
      ->required();
  command.add_option("--protocol", args.protocol, "Bus protocol: feetech, d55d or modbus-rtu")
      ->required()
      ->check(CLI::IsMember(names_of_protocols()));
  if (baud_required) {
    command.add_option("--baud", args.baud, "The servo's current bit rate (a rate of the protocol's baud table)")
        ->required();
  }
  command.add_option("--parity", args.parity, "Line parity (modbus-rtu): none, even, odd (N, E, O)")
      ->check(CLI::IsMember({"none", "even", "odd", "N", "E", "O"}))
      ->capture_default_str();
  command.add_option("--stop-bits", args.stop_bits, "Stop bits: 1 or 2")
      ->check(CLI::IsMember({1U, 2U}))
      ->capture_default_str();
  command
      .add_option("--latency-ms", args.latency_ms,
                  "Added to every reply timeout: the adapter's latency (FTDI adapters: 16 unless their latency "
                  "timer is set to 1)")
      ->capture_default_str();
  command
      .add_option("--table", args.table,
                  "The servos' table: sts or sms1 (feetech), d55d, smsmb (modbus-rtu); "
                  "default the protocol's usual one")
      ->check(CLI::IsMember({"sts", "sms1", "scs", "d55d", "smsmb"}));
}

LinkSettings link_settings(const LineArgs& args) {
  LinkSettings settings;
  settings.device = args.device;
  settings.protocol = *protocol::bus_protocol_from_string(args.protocol);
  settings.baud = args.baud;
  settings.parity = parity_from(args.parity);
  settings.stop_bits = static_cast<std::uint8_t>(args.stop_bits);
  settings.latency = std::chrono::milliseconds{args.latency_ms};
  return settings;
}

modbus_map::TableId table_of(const LineArgs& args, std::string_view command) {
  const auto protocol = *protocol::bus_protocol_from_string(args.protocol);
  if (args.table.empty()) return tool_protocol(protocol).default_table;
  const auto table = *modbus_map::table_from_name(args.table);
  if (modbus_map::table(table).protocol != protocol) {
    fail(command, "table " + args.table + " is not spoken on " + args.protocol + " buses", kExitUsage);
  }
  return table;
}

std::unique_ptr<ServoLink> open_link(const LinkSettings& settings, std::string_view command) {
  if (settings.baud != 0) {
    if (auto code = modbus_map::baud_code(settings.protocol, settings.baud); !code)
      fail(command, code.error(), kExitUsage);
  }
  auto link = make_servo_link(settings);
  if (auto opened = link->open(); !opened) fail(command, opened.error());
  return link;
}

Say printer() {
  return [](const std::string& line) { std::cerr << "  " << line << "\n"; };
}

void add_scan(CLI::App& app) {
  auto args = std::make_shared<LineArgs>();
  args->latency_ms = 5;
  auto bauds = std::make_shared<std::vector<std::uint32_t>>();
  auto ids = std::make_shared<std::string>();
  auto config_file = std::make_shared<std::string>();
  auto no_probe = std::make_shared<bool>(false);
  CLI::App* command = app.add_subcommand(
      "scan", "Find the servos on a line: every rate of the protocol's baud table (or --baud), every ID (or --ids)");
  add_line_options(*command, *args, false);
  command->add_option("--baud", *bauds, "Only these rates (repeat the option, or separate with commas)")
      ->delimiter(',');
  command->add_option("--ids", *ids, "Only these IDs, e.g. 1-10,20 (default: every ID of the protocol)");
  command->add_option("--write-config", *config_file, "Write a gateway configuration for the servos found to FILE");
  command->add_flag("--no-broadcast-probe", *no_probe,
                    "Ask every ID even where nobody answers a broadcast PING (feetech, d55d)");
  command->callback([args, bauds, ids, config_file, no_probe] {
    LinkSettings settings = link_settings(*args);
    ScanOptions options;
    options.bauds = *bauds;
    options.table = table_of(*args, "scan");
    options.broadcast_probe = !*no_probe;
    if (!ids->empty()) {
      auto parsed = parse_ids(*ids);
      if (!parsed) fail("scan", "--ids: " + parsed.error(), kExitUsage);
      options.ids = std::move(*parsed);
    }
    for (const std::uint32_t baud : options.bauds) {
      if (auto code = modbus_map::baud_code(settings.protocol, baud); !code) fail("scan", code.error(), kExitUsage);
    }
    settings.baud =
        options.bauds.empty() ? modbus_map::baud_table(settings.protocol).front().bps : options.bauds.front();
    auto link = open_link(settings, "scan");
    auto report = scan_bus(*link, options, printer());
    if (!report) fail("scan", report.error());
    std::cout << format_scan(*report) << std::flush;
    if (!config_file->empty()) {
      std::ofstream out(*config_file);
      out << scan_config_yaml(*report, settings);
      if (!out) fail("scan", "cannot write " + *config_file + ": " + std::strerror(errno));
      std::cerr << "configuration written to " << *config_file << "\n";
    }
    finish(kExitOk);
  });
}

void add_set_id(CLI::App& app) {
  auto args = std::make_shared<LineArgs>();
  auto new_id = std::make_shared<unsigned>(0);
  CLI::App* command = app.add_subcommand("set-id", "Give a servo another ID (kept over power-off)");
  add_line_options(*command, *args, true);
  command->add_option("--id", args->id, "The servo's current ID")->required();
  command->add_option("--new-id", *new_id, "The ID to give it")->required()->check(CLI::Range(0U, 253U));
  command->add_flag("--force", args->force,
                    "Allow --id to be the broadcast ID (254; modbus-rtu 0): every servo on "
                    "the line takes the new ID");
  command->callback([args, new_id] {
    auto link = open_link(link_settings(*args), "set-id");
    const ToolTarget target{table_of(*args, "set-id"), static_cast<std::uint8_t>(args->id), args->force};
    auto done = set_servo_id(*link, target, static_cast<std::uint8_t>(*new_id), printer());
    if (!done) fail("set-id", done.error());
    std::cout << *done << "\n";
    finish(kExitOk);
  });
}

void add_set_baud(CLI::App& app) {
  auto args = std::make_shared<LineArgs>();
  auto new_baud = std::make_shared<std::uint32_t>(0);
  CLI::App* command =
      app.add_subcommand("set-baud", "Move a servo to another rate of its baud table (kept over power-off)");
  add_line_options(*command, *args, true);
  command->add_option("--id", args->id, "The servo's ID")->required();
  command->add_option("--new-baud", *new_baud, "The rate to move it to")->required();
  command->add_flag("--force", args->force, "Allow --id to be the broadcast ID: every servo on the line moves");
  command->callback([args, new_baud] {
    auto link = open_link(link_settings(*args), "set-baud");
    const ToolTarget target{table_of(*args, "set-baud"), static_cast<std::uint8_t>(args->id), args->force};
    auto done = set_servo_baud(*link, target, *new_baud, printer());
    if (!done) fail("set-baud", done.error());
    std::cout << *done << "\n";
    finish(kExitOk);
  });
}

// A tool that acts on one servo and says what it did: calibrate-middle, factory-reset.
using ServoAction = Expected<std::string> (*)(ServoLink&, const ToolTarget&, const Say&);
void add_servo_action(CLI::App& app, const std::string& name, const std::string& description, ServoAction action,
                      const std::string& force_help) {
  auto args = std::make_shared<LineArgs>();
  CLI::App* command = app.add_subcommand(name, description);
  add_line_options(*command, *args, true);
  command->add_option("--id", args->id, "The servo's ID")->required();
  if (!force_help.empty()) command->add_flag("--force", args->force, force_help);
  command->callback([args, name, action] {
    auto link = open_link(link_settings(*args), name);
    const ToolTarget target{table_of(*args, name), static_cast<std::uint8_t>(args->id), args->force};
    auto done = action(*link, target, printer());
    if (!done) fail(name, done.error());
    std::cout << *done << "\n";
    finish(kExitOk);
  });
}

void add_dump(CLI::App& app) {
  auto args = std::make_shared<LineArgs>();
  CLI::App* command = app.add_subcommand("dump", "Print a servo's whole control table: address, name, value, unit");
  add_line_options(*command, *args, true);
  command->add_option("--id", args->id, "The servo's ID")->required();
  command->callback([args] {
    auto link = open_link(link_settings(*args), "dump");
    const ToolTarget target{table_of(*args, "dump"), static_cast<std::uint8_t>(args->id), false};
    auto rows = dump_servo(*link, target);
    if (!rows) fail("dump", rows.error());
    std::cout << format_dump(modbus_map::table(target.table), *rows) << std::flush;
    finish(kExitOk);
  });
}

struct ForwardArgs {
  std::string device;
  std::uint32_t baud = 0;
  std::string parity = "none";
  unsigned stop_bits = 1;
  std::string listen = "127.0.0.1:5020";
  bool rs485 = false;
  std::string rts = "none";
  std::optional<unsigned> rts_delay_us;
  unsigned byte_timeout_ms = 50;
  unsigned response_timeout_ms = 100;
  unsigned retries = 1;
  std::size_t max_connections = 32;
  std::size_t queue_depth = 64;
  std::string log_level = "info";
  unsigned idle_timeout_s = 60;
  bool reply_on_broadcast = false;
  std::string frame_gap = "spec";
};

void add_forward(CLI::App& app) {
  auto args = std::make_shared<ForwardArgs>();
  CLI::App* command = app.add_subcommand(
      "forward", "Plain Modbus TCP -> RTU gateway, no configuration: unit u is RTU slave u, unit 0 the broadcast");
  command->add_option("--device", args->device, "Serial device of the RTU line")->required();
  command->add_option("--baud", args->baud, "Bit rate of the line (any rate the adapter runs)")
      ->required()
      ->check(CLI::Range(1U, 20'000'000U));
  command->add_option("--parity", args->parity, "none, even, odd (N, E, O)")
      ->check(CLI::IsMember({"none", "even", "odd", "N", "E", "O"}))
      ->capture_default_str();
  command->add_option("--stop-bits", args->stop_bits, "1 or 2")->check(CLI::IsMember({1U, 2U}))->capture_default_str();
  command->add_option("--listen", args->listen, "HOST:PORT to serve Modbus TCP on")->capture_default_str();
  command->add_flag("--rs485", args->rs485, "Kernel RS-485 mode (TIOCSRS485) for UARTs that drive the transceiver");
  command->add_option("--rts", args->rts, "RTS direction control: none, up, down")
      ->check(CLI::IsMember({"none", "up", "down"}))
      ->capture_default_str();
  command->add_option("--rts-delay-us", args->rts_delay_us, "Delay around the RTS switch (default one character)");
  command->add_option("--byte-timeout-ms", args->byte_timeout_ms, "Longest silence inside one answer")
      ->check(CLI::Range(1U, 10'000U))
      ->capture_default_str();
  command
      ->add_option("--response-timeout-ms", args->response_timeout_ms,
                   "Time a slave may take to start answering, beyond the frames' wire time")
      ->check(CLI::Range(1U, 60'000U))
      ->capture_default_str();
  command->add_option("--retries", args->retries, "Attempts after the first on timeouts and CRC errors")
      ->capture_default_str();
  command->add_option("--max-connections", args->max_connections, "Concurrent Modbus TCP clients")
      ->capture_default_str();
  command->add_option("--queue-depth", args->queue_depth, "Requests waiting for the line; past it 0x06 (busy)")
      ->check(CLI::Range(std::size_t{1}, std::size_t{100'000}))
      ->capture_default_str();
  command
      ->add_option("--frame-gap", args->frame_gap,
                   "Silence before each frame, from the last byte on the wire: spec (3.5 characters, 1.75 ms "
                   "above 19200 bit/s), 3.5chars, or a time such as 500us")
      ->capture_default_str();
  command->add_option("--idle-timeout-s", args->idle_timeout_s, "Close a client silent this long (0: never)")
      ->check(CLI::Range(0U, 86'400U))
      ->capture_default_str();
  command->add_flag("-b,--reply-on-broadcast", args->reply_on_broadcast,
                    "Answer writes to unit 0 once sent (default, as mbusd: no answer to a broadcast)");
  command->add_option("--log-level", args->log_level, "trace, debug, info, warn, error, critical or off")
      ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error", "critical", "off"}))
      ->capture_default_str();
  command->callback([args] {
    auto listen = config::parse_host_port(args->listen);
    if (!listen) fail("forward", "--listen " + args->listen + ": " + listen.error(), kExitUsage);
    if (args->rts_delay_us && args->rts == "none") fail("forward", "--rts-delay-us needs --rts up or down", kExitUsage);
    const auto frame_gap = config::parse_frame_gap(args->frame_gap);
    if (!frame_gap) fail("forward", "--frame-gap: " + frame_gap.error(), kExitUsage);
    spdlog::set_level(spdlog::level::from_str(args->log_level));

    ForwardOptions options;
    options.serial =
        SerialSettings{args->device, args->baud, parity_from(args->parity), static_cast<std::uint8_t>(args->stop_bits)};
    options.rtu.rs485 = args->rs485;
    options.rtu.rts = rts_from(args->rts);
    if (args->rts_delay_us) options.rtu.rts_delay = std::chrono::microseconds{*args->rts_delay_us};
    options.rtu.byte_timeout = std::chrono::milliseconds{args->byte_timeout_ms};
    options.rtu.frame_gap = *frame_gap;
    options.response_timeout = std::chrono::milliseconds{args->response_timeout_ms};
    options.retries = args->retries;
    options.listen = *listen;
    options.max_connections = args->max_connections;
    options.queue_depth = args->queue_depth;
    options.idle_timeout = std::chrono::seconds{args->idle_timeout_s};
    options.broadcast_reply = args->reply_on_broadcast ? BroadcastReply::Answer : BroadcastReply::None;

    const process::StopSignals stop_signals;  // blocked before the gateway's threads start
    try {
      ForwardGateway gateway(options);
      gateway.start();
      // The bound port: --listen HOST:0 picks a free one.
      spdlog::info(
          "forwarding Modbus TCP on {}:{} to {} at {} bit/s ({}{}{}): unit u -> slave u, unit 0 -> broadcast "
          "({})",
          listen->host, gateway.port(), args->device, args->baud, 8, parity_letter(options.serial.parity),
          args->stop_bits, args->reply_on_broadcast ? "answered once sent" : "not answered");
      spdlog::info("{} received: answering the requests in flight, then stopping",
                   process::StopSignals::name(stop_signals.wait()));
      gateway.stop();
    } catch (const std::exception& error) {
      fail("forward", error.what());
    }
    finish(kExitOk);
  });
}

struct TagsArgs {
  std::string config_file;
  std::string format;
  std::string output;
  std::string host = "127.0.0.1";
  unsigned port = 502;
};

constexpr const char* kTagFormats = "csv, node-red or fuxa";

void add_tags(CLI::App& app) {
  auto args = std::make_shared<TagsArgs>();
  CLI::App* command = app.add_subcommand(
      "tags",
      "Print every Modbus address a configuration serves as tags for an HMI: csv, node-red, fuxa (docs/HMI.md)");
  command->add_option("--config", args->config_file, "The gateway configuration (YAML)")->required();
  // Checked in the callback, not by CLI11: a wrong format is a usage error (2) naming the formats.
  command->add_option("--format", args->format, std::string("Output format: ") + kTagFormats)->required();
  command->add_option("--output", args->output, "Write to FILE instead of standard output");
  command->add_option("--host", args->host, "Gateway address the Node-RED and FUXA connections use")
      ->capture_default_str();
  command->add_option("--port", args->port, "Gateway Modbus TCP port the Node-RED and FUXA connections use")
      ->check(CLI::Range(1U, 65535U))
      ->capture_default_str();
  command->callback([args] {
    if (args->format != "csv" && args->format != "node-red" && args->format != "fuxa") {
      fail("tags", "--format " + args->format + ": the formats are " + kTagFormats, kExitUsage);
    }
    const auto config = config::load_config_file(args->config_file);
    if (!config) fail("tags", config.error().to_string(), kExitUsage);
    std::string text;
    try {
      const UnitCatalog catalog(*config);
      const FlowTarget target{args->host, static_cast<std::uint16_t>(args->port)};
      if (args->format == "csv") {
        text = tags_csv(tag_list(*config, catalog));
      } else if (args->format == "node-red") {
        text = node_red_flow(*config, catalog, target).dump(2) + "\n";
      } else {
        text = fuxa_devices(tag_list(*config, catalog), target).dump(2) + "\n";
      }
    } catch (const std::exception& error) {
      fail("tags", args->config_file + ": " + error.what());
    }
    if (args->output.empty()) {
      std::cout << text << std::flush;
    } else {
      std::ofstream out(args->output, std::ios::binary);
      out << text;
      if (!out) fail("tags", "cannot write " + args->output + ": " + std::strerror(errno));
    }
    finish(kExitOk);
  });
}

}  // namespace

void add_tool_commands(CLI::App& app) {
  add_forward(app);
  add_scan(app);
  add_set_id(app);
  add_set_baud(app);
  add_servo_action(app, "calibrate-middle",
                   "Make a servo's present position its centre (sts: 128 to address 40; smsmb: 0x86 bit 2)",
                   calibrate_middle, "Allow --id to be the broadcast ID: every servo on the line");
  add_servo_action(app, "factory-reset",
                   "Put a servo's whole table back to factory values, ID and baud included (d55d RESET; "
                   "feetech and modbus-rtu servos have no such instruction)",
                   factory_reset, "");
  add_dump(app);
  add_tags(app);
}

}  // namespace sms::gateway
