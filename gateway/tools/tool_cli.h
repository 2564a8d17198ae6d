#pragma once
// The integrator tools and the transparent forwarder as subcommands of sms-gateway:
//   forward           Modbus TCP -> RTU gateway without a configuration file (passthrough.h)
//   scan              find servos on a line: every rate of the protocol's table, every ID (tool_scan.h)
//   set-id, set-baud, calibrate-middle, factory-reset, dump   one servo (tool_servo.h)
//   tags              a configuration's addresses as HMI tag lists (tag_list.h)
// `sms-gateway SUBCOMMAND --help` lists each one's options.
//
// A subcommand runs inside app.parse() (its callback) and ends the parse with
// CLI::RuntimeError(exit status): main's `catch (const CLI::ParseError& e) { return app.exit(e); }`
// returns that status without printing anything more. Exit status: 0 done, 1 the tool failed or
// refused (the reason is on stderr), 2 an argument the tool refuses (a rate outside the table,
// a bad ID list); CLI11's own usage errors keep CLI11's status.
namespace CLI {
class App;
}

namespace sms::gateway {

void add_tool_commands(CLI::App& app);

}  // namespace sms::gateway
