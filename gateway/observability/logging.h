#pragma once
// Log setup for sms-gateway: level, and plain lines for people or JSON lines for log
// collectors (logging.format, SMS_GATEWAY_LOG_FORMAT). Everything logs through spdlog's
// default logger; setup_logging() replaces it.
//
//   sms::gateway::setup_logging(config.logging);          // to standard error
//   sms::gateway::setup_logging(config.logging, sink);    // tests: a recording sink
//
// A JSON line is one object with exactly these keys, in this order:
//   {"ts":"2024-05-01T12:00:00.123Z","level":"info","logger":"sms-gateway","msg":"..."}
// ts is UTC with milliseconds; level is the configuration's name for it (trace, debug, info,
// warn, error, critical); msg is the formatted message, escaped per RFC 8259 (invalid UTF-8
// bytes become U+FFFD, so a line is always valid JSON).
#include <memory>
#include <string>
#include <string_view>

#include "config/config.h"

namespace spdlog {
class formatter;
class logger;
namespace sinks {
class sink;
}
}  // namespace spdlog

namespace sms::gateway {

inline constexpr std::string_view kLoggerName = "sms-gateway";
// The plain line: "[2024-05-01 12:00:00.123] [info] message" (local time; spdlog's level names,
// "warning" for warn; the level is coloured on a terminal).
inline constexpr std::string_view kPlainPattern = "[%Y-%m-%d %H:%M:%S.%e] [%^%l%$] %v";

// A formatter writing one JSON object per record, newline-terminated.
std::unique_ptr<spdlog::formatter> make_json_line_formatter();

// `text` as the inside of a JSON string (no surrounding quotes).
std::string json_escape(std::string_view text);

// Makes a logger named kLoggerName on `sink` (nullptr: standard error) with the configured
// level and format the default logger, flushing after every record (containers and journald
// see each line at once). Returns it.
std::shared_ptr<spdlog::logger> setup_logging(const config::LoggingConfig& logging,
                                              std::shared_ptr<spdlog::sinks::sink> sink = nullptr);

}  // namespace sms::gateway
