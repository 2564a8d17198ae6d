#include "config/env.h"

#include <charconv>
#include <cstdlib>
#include <limits>

#include "config/names.h"

namespace sms::config {
namespace {

// Parses `value` into `config`; on failure says what is wrong with the value (the caller adds
// the variable's name and form).
using Apply = Expected<Ok> (*)(Config& config, std::string_view value);

std::string_view trim(std::string_view text) {
  constexpr std::string_view kSpace = " \t\r\n";
  const auto first = text.find_first_not_of(kSpace);
  if (first == std::string_view::npos) return {};
  return text.substr(first, text.find_last_not_of(kSpace) - first + 1);
}

Expected<std::int64_t> integer(std::string_view text, std::int64_t min, std::int64_t max) {
  std::int64_t value = 0;
  const auto* end = text.data() + text.size();
  const auto [stop, error] = std::from_chars(text.data(), end, value);
  const std::string range = std::to_string(min) + ".." + std::to_string(max);
  if (text.empty() || error != std::errc{} || stop != end) return unexpected("not a whole number " + range);
  if (value < min || value > max) return unexpected(std::string(text) + " is outside " + range);
  return value;
}

template <typename E, std::size_t N>
Expected<E> choice(std::string_view text, const std::array<detail::Named<E>, N>& names) {
  if (const auto value = detail::value_of(names, text)) return *value;
  return unexpected("not one of " + detail::names_text(names));
}

Expected<Ok> apply_listen(Config& config, std::string_view value) {
  auto parsed = parse_host_port(value);
  if (!parsed) return unexpected(parsed.error());
  config.modbus_tcp.listen = std::move(*parsed);
  return Ok{};
}

Expected<Ok> apply_log_level(Config& config, std::string_view value) {
  const auto level = choice(value, detail::kLogLevelNames);
  if (!level) return unexpected(level.error());
  config.logging.level = *level;
  return Ok{};
}

Expected<Ok> apply_log_format(Config& config, std::string_view value) {
  const auto format = choice(value, detail::kLogFormatNames);
  if (!format) return unexpected(format.error());
  config.logging.format = *format;
  return Ok{};
}

Expected<Ok> apply_metrics(Config& config, std::string_view value) {
  if (value == "off") {
    config.logging.metrics_listen.reset();
    return Ok{};
  }
  auto parsed = parse_host_port(value);
  if (!parsed) return unexpected(parsed.error());
  config.logging.metrics_listen = std::move(*parsed);
  return Ok{};
}

Expected<Ok> apply_max_connections(Config& config, std::string_view value) {
  const auto number = integer(value, 1, static_cast<std::int64_t>(kMaxConnectionsLimit));
  if (!number) return unexpected(number.error());
  config.modbus_tcp.max_connections = static_cast<std::size_t>(*number);
  return Ok{};
}

Expected<Ok> apply_idle_timeout(Config& config, std::string_view value) {
  const auto number = integer(value, 0, kMaxIdleTimeoutSeconds);
  if (!number) return unexpected(number.error());
  config.modbus_tcp.idle_timeout = std::chrono::seconds{*number};
  return Ok{};
}

Expected<Ok> apply_allow(Config& config, std::string_view value) {
  std::vector<IpNetwork> networks;
  std::size_t start = 0;
  while (start <= value.size()) {
    const auto comma = value.find(',', start);
    const auto item =
        trim(value.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start));
    const std::string position = "item " + std::to_string(networks.size() + 1);
    if (item.empty()) return unexpected(position + " is empty");
    auto network = parse_ip_network(item);
    if (!network) return unexpected(position + ": " + network.error());
    networks.push_back(*network);
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  config.modbus_tcp.allow = std::move(networks);
  return Ok{};
}

struct EnvEntry {
  EnvVariable variable;
  Apply apply;
};

constexpr EnvEntry kEntries[] = {
    {{"SMS_GATEWAY_LISTEN", "HOST:PORT (e.g. 0.0.0.0:502, \"[::]:502\")", "modbus_tcp.listen"}, apply_listen},
    {{"SMS_GATEWAY_MAX_CONNECTIONS", "a whole number 1..4096", "modbus_tcp.max_connections"}, apply_max_connections},
    {{"SMS_GATEWAY_IDLE_TIMEOUT_S", "seconds 0..86400 (0: never close idle clients)", "modbus_tcp.idle_timeout_s"},
     apply_idle_timeout},
    {{"SMS_GATEWAY_ALLOW", "a comma-separated list of addresses or CIDR networks (e.g. 192.168.10.0/24,fd00::/8)",
      "modbus_tcp.allow"},
     apply_allow},
    {{"SMS_GATEWAY_LOG_LEVEL", "trace, debug, info, warn, error, critical or off", "logging.level"}, apply_log_level},
    {{"SMS_GATEWAY_LOG_FORMAT", "plain or json", "logging.format"}, apply_log_format},
    {{"SMS_GATEWAY_METRICS", "HOST:PORT (e.g. 0.0.0.0:9102), or off", "logging.metrics_listen"}, apply_metrics},
};

constexpr auto kVariables = [] {
  std::array<EnvVariable, std::size(kEntries)> out{};
  for (std::size_t i = 0; i < out.size(); ++i) out[i] = kEntries[i].variable;
  return out;
}();

}  // namespace

std::span<const EnvVariable> environment_variables() { return kVariables; }

EnvLookup process_environment() {
  return [](std::string_view name) -> std::optional<std::string> {
    const char* value = std::getenv(std::string(name).c_str());
    if (value == nullptr) return std::nullopt;
    return std::string(value);
  };
}

Expected<std::vector<std::string>> apply_environment(Config& config, const EnvLookup& lookup) {
  Config result = config;
  std::vector<std::string> applied;
  for (const auto& entry : kEntries) {
    const auto raw = lookup(entry.variable.name);
    if (!raw) continue;
    const auto value = trim(*raw);
    if (value.empty()) continue;
    const auto outcome = entry.apply(result, value);
    if (!outcome) {
      return unexpected(std::string(entry.variable.name) + "=\"" + *raw + "\": " + outcome.error() + "; expected " +
                        std::string(entry.variable.form) + " (replaces " + std::string(entry.variable.setting) + ")");
    }
    applied.emplace_back(entry.variable.name);
  }
  config = std::move(result);
  return applied;
}

}  // namespace sms::config
