// Log setup: level filtering, plain lines, and JSON lines (one object per line, ts / level /
// logger / msg, escaped so every line is valid JSON). A recording sink keeps what was logged.
#include <gtest/gtest.h>

#include <mutex>
#include <regex>
#include <string>
#include <vector>

#include <spdlog/sinks/base_sink.h>
#include <spdlog/spdlog.h>

#include "gateway/observability/logging.h"

namespace sms::gateway {
namespace {

// Keeps every formatted record, as the logger's formatter wrote it.
class RecordingSink final : public spdlog::sinks::base_sink<std::mutex> {
 public:
  std::vector<std::string> lines() {
    std::lock_guard lock(mutex_);
    return lines_;
  }

 protected:
  void sink_it_(const spdlog::details::log_msg& msg) override {
    spdlog::memory_buf_t formatted;
    formatter_->format(msg, formatted);
    lines_.emplace_back(formatted.data(), formatted.size());
  }
  void flush_() override { ++flushes_; }

 private:
  std::vector<std::string> lines_;
  int flushes_ = 0;
};

// Every test replaces the process's default logger; put the previous one back.
class Logging : public ::testing::Test {
 protected:
  Logging() : previous_(spdlog::default_logger()) {}
  ~Logging() override { spdlog::set_default_logger(previous_); }

  std::shared_ptr<RecordingSink> setup(config::LogLevel level, config::LogFormat format) {
    auto sink = std::make_shared<RecordingSink>();
    setup_logging(config::LoggingConfig{.level = level, .format = format, .metrics_listen = std::nullopt}, sink);
    return sink;
  }

 private:
  std::shared_ptr<spdlog::logger> previous_;
};

// "2024-05-01T12:00:00.123Z"
const std::regex kTimestamp(R"(\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d{3}Z)");

TEST_F(Logging, JsonLineHasTsLevelLoggerAndMsgInThatOrder) {
  const auto sink = setup(config::LogLevel::Info, config::LogFormat::Json);
  spdlog::info("modbus tcp: listening on {}:{}", "0.0.0.0", 502);
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 1u);
  const std::regex line(
      R"re(\{"ts":"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d{3}Z","level":"info","logger":"sms-gateway","msg":"modbus tcp: listening on 0\.0\.0\.0:502"\}\n)re");
  EXPECT_TRUE(std::regex_match(lines[0], line)) << lines[0];
}

TEST_F(Logging, JsonLevelNamesAreTheConfigurationsNames) {
  const auto sink = setup(config::LogLevel::Trace, config::LogFormat::Json);
  spdlog::trace("t");
  spdlog::debug("d");
  spdlog::info("i");
  spdlog::warn("w");
  spdlog::error("e");
  spdlog::critical("c");
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 6u);
  const std::vector<std::string> levels{"trace", "debug", "info", "warn", "error", "critical"};
  for (std::size_t i = 0; i < levels.size(); ++i) {
    EXPECT_NE(lines[i].find(",\"level\":\"" + levels[i] + "\","), std::string::npos) << lines[i];
  }
}

TEST_F(Logging, JsonEscapesQuotesBackslashesAndControlCharacters) {
  const auto sink = setup(config::LogLevel::Info, config::LogFormat::Json);
  spdlog::info("device \"{}\" at C:\\ports\nline two\ttab\x01{}", "/dev/ttyUSB0", "\x1f");
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 1u);
  const std::string expected_msg = R"("msg":"device \"/dev/ttyUSB0\" at C:\\ports\nline two\ttab\u0001\u001f"})"
                                   "\n";
  ASSERT_GE(lines[0].size(), expected_msg.size());
  EXPECT_EQ(lines[0].substr(lines[0].size() - expected_msg.size()), expected_msg) << lines[0];
  // One record is one line: the newline in the message is escaped.
  EXPECT_EQ(std::count(lines[0].begin(), lines[0].end(), '\n'), 1);
}

TEST_F(Logging, JsonKeepsValidUtf8AndReplacesInvalidBytes) {
  EXPECT_EQ(json_escape("Achse ü 軸 🙂"), "Achse ü 軸 🙂");
  EXPECT_EQ(json_escape("a\xff"
                        "b"),
            "a\\ufffdb");
  EXPECT_EQ(json_escape("\xc3"), "\\ufffd");                                   // truncated two-byte sequence
  EXPECT_EQ(json_escape("\xc0\xaf"), "\\ufffd\\ufffd");                        // overlong '/'
  EXPECT_EQ(json_escape("\xed\xa0\x80"), "\\ufffd\\ufffd\\ufffd");             // UTF-16 surrogate
  EXPECT_EQ(json_escape("\xf4\x90\x80\x80"), "\\ufffd\\ufffd\\ufffd\\ufffd");  // above U+10FFFF
  EXPECT_EQ(json_escape("\xe2\x82"), "\\ufffd\\ufffd");                        // truncated at the end
  EXPECT_EQ(json_escape("\x7f"), "\x7f");                                      // DEL needs no escape in JSON
  EXPECT_EQ(json_escape(std::string("a\0b", 3)), "a\\u0000b");
  EXPECT_EQ(json_escape("\b\f\r"), "\\b\\f\\r");
}

TEST_F(Logging, JsonTimestampIsUtc) {
  const auto sink = setup(config::LogLevel::Info, config::LogFormat::Json);
  const auto before = std::chrono::system_clock::now();
  spdlog::info("x");
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 1u);
  std::smatch match;
  const std::string& line = lines[0];
  ASSERT_TRUE(std::regex_search(line, match, kTimestamp)) << line;
  // The same instant formatted here with gmtime: at least the date and hour agree (the test
  // does not run across an hour boundary in practice; allow it once by also accepting +1 h).
  const std::time_t now = std::chrono::system_clock::to_time_t(before);
  std::tm utc{};
  ::gmtime_r(&now, &utc);
  char expected[20];
  std::strftime(expected, sizeof expected, "%Y-%m-%dT%H", &utc);
  const std::time_t later = now + 3600;
  std::tm utc_later{};
  ::gmtime_r(&later, &utc_later);
  char expected_later[20];
  std::strftime(expected_later, sizeof expected_later, "%Y-%m-%dT%H", &utc_later);
  const std::string prefix = match.str().substr(0, 13);
  EXPECT_TRUE(prefix == expected || prefix == expected_later) << prefix << " vs " << expected;
}

TEST_F(Logging, LevelFiltersRecordsBelowIt) {
  const auto sink = setup(config::LogLevel::Warn, config::LogFormat::Json);
  spdlog::debug("not shown");
  spdlog::info("not shown either");
  spdlog::warn("shown");
  spdlog::error("shown too");
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_NE(lines[0].find("\"msg\":\"shown\""), std::string::npos);
  EXPECT_NE(lines[1].find("\"msg\":\"shown too\""), std::string::npos);
}

TEST_F(Logging, OffLogsNothing) {
  const auto sink = setup(config::LogLevel::Off, config::LogFormat::Plain);
  spdlog::critical("nothing");
  EXPECT_TRUE(sink->lines().empty());
}

TEST_F(Logging, PlainLineHasTimeLevelAndMessage) {
  const auto sink = setup(config::LogLevel::Info, config::LogFormat::Plain);
  spdlog::warn("bus {} is down", "arm");
  const auto lines = sink->lines();
  ASSERT_EQ(lines.size(), 1u);
  const std::regex line(R"(\[\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2}\.\d{3}\] \[warning\] bus arm is down\n)");
  EXPECT_TRUE(std::regex_match(lines[0], line)) << lines[0];
}

TEST_F(Logging, SetupMakesTheDefaultLoggerAndFlushesEveryRecord) {
  const auto sink = setup(config::LogLevel::Info, config::LogFormat::Plain);
  EXPECT_EQ(spdlog::default_logger()->name(), "sms-gateway");
  EXPECT_EQ(spdlog::default_logger()->flush_level(), spdlog::level::trace);
  EXPECT_EQ(spdlog::default_logger()->level(), spdlog::level::info);
}

TEST_F(Logging, SetupTwiceReplacesTheFirst) {
  const auto first = setup(config::LogLevel::Info, config::LogFormat::Plain);
  const auto second = setup(config::LogLevel::Info, config::LogFormat::Json);
  spdlog::info("to the second");
  EXPECT_TRUE(first->lines().empty());
  ASSERT_EQ(second->lines().size(), 1u);
  EXPECT_EQ(second->lines()[0].front(), '{');
}

TEST_F(Logging, JsonFormatterCloneFormatsTheSame) {
  const auto formatter = make_json_line_formatter();
  const auto clone = formatter->clone();
  spdlog::details::log_msg msg(spdlog::source_loc{}, "unit-test", spdlog::level::err, "clone \"ok\"");
  spdlog::memory_buf_t a;
  spdlog::memory_buf_t b;
  formatter->format(msg, a);
  clone->format(msg, b);
  const std::string text(a.data(), a.size());
  EXPECT_EQ(text, std::string(b.data(), b.size()));
  EXPECT_NE(text.find(R"("level":"error","logger":"unit-test","msg":"clone \"ok\""})"), std::string::npos) << text;
}

}  // namespace
}  // namespace sms::gateway
