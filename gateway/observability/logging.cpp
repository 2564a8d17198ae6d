#include "gateway/observability/logging.h"

#include <time.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>

#include <spdlog/formatter.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

namespace sms::gateway {
namespace {

using config::LogLevel;

struct LevelName {
  spdlog::level::level_enum spdlog;
  LogLevel config;
};
constexpr std::array<LevelName, 7> kLevels{{
    {spdlog::level::trace, LogLevel::Trace},
    {spdlog::level::debug, LogLevel::Debug},
    {spdlog::level::info, LogLevel::Info},
    {spdlog::level::warn, LogLevel::Warn},
    {spdlog::level::err, LogLevel::Error},
    {spdlog::level::critical, LogLevel::Critical},
    {spdlog::level::off, LogLevel::Off},
}};

spdlog::level::level_enum spdlog_level(LogLevel level) {
  for (const auto& entry : kLevels) {
    if (entry.config == level) return entry.spdlog;
  }
  return spdlog::level::info;
}

// The configuration's spelling ("warn", not spdlog's "warning"), so a JSON line's level reads
// the same as the logging.level that selects it.
std::string_view level_name(spdlog::level::level_enum level) {
  for (const auto& entry : kLevels) {
    if (entry.spdlog == level) return config::to_string(entry.config);
  }
  return "unknown";
}

// Length of the valid UTF-8 sequence at the start of `text`, 0 when it is not one (RFC 3629 §4:
// no overlong forms, no surrogates, nothing above U+10FFFF).
std::size_t utf8_sequence_length(std::string_view text) {
  const auto byte = [&](std::size_t i) { return static_cast<unsigned char>(text[i]); };
  const unsigned char lead = byte(0);
  std::size_t length = 0;
  unsigned char second_min = 0x80;
  unsigned char second_max = 0xBF;
  if (lead < 0x80) return 1;
  if (lead >= 0xC2 && lead <= 0xDF) {
    length = 2;
  } else if (lead >= 0xE0 && lead <= 0xEF) {
    length = 3;
    if (lead == 0xE0) second_min = 0xA0;  // overlong
    if (lead == 0xED) second_max = 0x9F;  // surrogates
  } else if (lead >= 0xF0 && lead <= 0xF4) {
    length = 4;
    if (lead == 0xF0) second_min = 0x90;  // overlong
    if (lead == 0xF4) second_max = 0x8F;  // above U+10FFFF
  } else {
    return 0;
  }
  if (text.size() < length) return 0;
  if (byte(1) < second_min || byte(1) > second_max) return 0;
  for (std::size_t i = 2; i < length; ++i) {
    if (byte(i) < 0x80 || byte(i) > 0xBF) return 0;
  }
  return length;
}

struct ShortEscape {
  char raw;
  std::string_view escaped;
};
constexpr ShortEscape kShortEscapes[] = {
    {'"', "\\\""}, {'\\', "\\\\"}, {'\b', "\\b"}, {'\f', "\\f"}, {'\n', "\\n"}, {'\r', "\\r"}, {'\t', "\\t"},
};

void append_json_escaped(std::string& out, std::string_view text) {
  constexpr char kHex[] = "0123456789abcdef";
  std::size_t i = 0;
  while (i < text.size()) {
    const char c = text[i];
    const auto* escape = std::find_if(std::begin(kShortEscapes), std::end(kShortEscapes),
                                      [c](const ShortEscape& e) { return e.raw == c; });
    if (escape != std::end(kShortEscapes)) {
      out += escape->escaped;
      ++i;
      continue;
    }
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20) {
      out += "\\u00";
      out += kHex[u >> 4];
      out += kHex[u & 0x0F];
      ++i;
      continue;
    }
    const std::size_t length = utf8_sequence_length(text.substr(i));
    if (length == 0) {
      out += "\\ufffd";  // one replacement per invalid byte
      ++i;
      continue;
    }
    out.append(text.substr(i, length));
    i += length;
  }
}

// "2024-05-01T12:00:00.123Z"
void append_timestamp(std::string& out, spdlog::log_clock::time_point time) {
  const auto since_epoch = time.time_since_epoch();
  const auto whole = std::chrono::duration_cast<std::chrono::seconds>(since_epoch);
  const auto millis = std::chrono::duration_cast<std::chrono::milliseconds>(since_epoch - whole).count();
  const std::time_t seconds = static_cast<std::time_t>(whole.count());
  std::tm utc{};
  ::gmtime_r(&seconds, &utc);
  char text[40];
  const int length =
      std::snprintf(text, sizeof text, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", utc.tm_year + 1900, utc.tm_mon + 1,
                    utc.tm_mday, utc.tm_hour, utc.tm_min, utc.tm_sec, static_cast<int>(millis));
  if (length > 0) out.append(text, std::min<std::size_t>(static_cast<std::size_t>(length), sizeof text - 1));
}

class JsonLineFormatter final : public spdlog::formatter {
 public:
  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    line_.clear();
    line_ += "{\"ts\":\"";
    append_timestamp(line_, msg.time);
    line_ += "\",\"level\":\"";
    line_ += level_name(msg.level);
    line_ += "\",\"logger\":\"";
    append_json_escaped(line_, std::string_view(msg.logger_name.data(), msg.logger_name.size()));
    line_ += "\",\"msg\":\"";
    append_json_escaped(line_, std::string_view(msg.payload.data(), msg.payload.size()));
    line_ += "\"}\n";
    dest.append(line_.data(), line_.data() + line_.size());
  }

  std::unique_ptr<spdlog::formatter> clone() const override { return std::make_unique<JsonLineFormatter>(); }

 private:
  std::string line_;  // reused: one allocation per formatter, not per record
};

}  // namespace

std::unique_ptr<spdlog::formatter> make_json_line_formatter() { return std::make_unique<JsonLineFormatter>(); }

std::string json_escape(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  append_json_escaped(out, text);
  return out;
}

std::shared_ptr<spdlog::logger> setup_logging(const config::LoggingConfig& logging,
                                              std::shared_ptr<spdlog::sinks::sink> sink) {
  const bool json = logging.format == config::LogFormat::Json;
  if (!sink) {
    // Colours only on a terminal (the colour sink checks); a JSON line is never coloured.
    if (json) {
      sink = std::make_shared<spdlog::sinks::stderr_sink_mt>();
    } else {
      sink = std::make_shared<spdlog::sinks::stderr_color_sink_mt>();
    }
  }
  auto logger = std::make_shared<spdlog::logger>(std::string(kLoggerName), std::move(sink));
  if (json) {
    logger->set_formatter(make_json_line_formatter());
  } else {
    logger->set_pattern(std::string(kPlainPattern));
  }
  logger->set_level(spdlog_level(logging.level));
  logger->flush_on(spdlog::level::trace);
  spdlog::set_default_logger(logger);
  return logger;
}

}  // namespace sms::gateway
