#pragma once
// Loading and validating the YAML configuration (keys: config/README.md).
//
//   auto config = sms::config::load_config_file("/etc/sms-gateway/gateway.yaml");
//   if (!config) { std::cerr << config.error().to_string() << '\n'; return 2; }
//
// Every rejection names the file, the line and column of the offending node, what is wrong and
// what is allowed there. The first problem found is reported.
#include <cstdint>
#include <string>
#include <string_view>

#include "config/config.h"
#include "protocol/expected.h"

namespace sms::config {

struct ConfigError {
  std::string file;
  std::uint32_t line = 0;    // 1-based; 0 when the problem has no place in the text (file unreadable)
  std::uint32_t column = 0;  // 1-based
  std::string message;

  // "file:line:col: message", or "file: message" without a place.
  std::string to_string() const;
};

Expected<Config, ConfigError> load_config_file(const std::string& path);
// `source_name` stands for the file name in errors ("<embedded>", "<command line>", a path).
Expected<Config, ConfigError> load_config_string(std::string_view text, std::string_view source_name);

// The configuration as YAML with every key written out, defaults included (what the gateway
// runs with). Loading the text gives back an equal Config.
std::string dump_config(const Config& config);

}  // namespace sms::config
