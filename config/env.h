#pragma once
// Configuration from environment variables, for containers: each variable that is set replaces
// one setting of the configuration file (or of the built-in --simulate configuration). Command
// line options still win over both. An empty variable counts as not set (compose files often
// write `SMS_GATEWAY_ALLOW=` to mean "nothing").
//
//   auto applied = sms::config::apply_environment(config);
//   if (!applied) { std::cerr << applied.error() << '\n'; return 2; }
//
// An invalid value is refused with the variable's name, its value and the valid form; the
// configuration is then left as it was.
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "protocol/expected.h"

namespace sms::config {

struct EnvVariable {
  std::string_view name;     // SMS_GATEWAY_LISTEN
  std::string_view form;     // HOST:PORT
  std::string_view setting;  // the configuration key it replaces: modbus_tcp.listen
};

// Every variable the gateway reads, in documentation order (config/README.md).
std::span<const EnvVariable> environment_variables();

// The value of one variable, nullopt when it is not set.
using EnvLookup = std::function<std::optional<std::string>(std::string_view name)>;
// getenv().
EnvLookup process_environment();

// Applies every variable that is set (and not empty) over `config`. Returns the names of the
// variables applied, in table order, for a log line. On an invalid value `config` is unchanged.
Expected<std::vector<std::string>> apply_environment(Config& config, const EnvLookup& lookup = process_environment());

}  // namespace sms::config
