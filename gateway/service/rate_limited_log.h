#pragma once
// A warning a client can cause many times a second — a PLC or panel writing cyclically what it
// may not — is logged at most once per interval; the lines held back in between are counted and
// said at the end of the next one. One per source (connection, port, router); not thread-safe:
// each lives on the thread that handles its requests.
#include <chrono>
#include <cstdint>
#include <string>

#include <spdlog/spdlog.h>

namespace sms::gateway {

class RateLimitedLog {
 public:
  explicit RateLimitedLog(std::chrono::steady_clock::duration interval = std::chrono::seconds{1})
      : interval_(interval) {}

  void warn(const std::string& line) {
    const auto now = std::chrono::steady_clock::now();
    if (logged_once_ && now - last_ < interval_) {
      ++held_back_;
      return;
    }
    spdlog::warn("{}{}", line,
                 held_back_ == 0 ? std::string() : " (" + std::to_string(held_back_) + " more since the last line)");
    logged_once_ = true;
    last_ = now;
    held_back_ = 0;
  }

 private:
  std::chrono::steady_clock::duration interval_;
  std::chrono::steady_clock::time_point last_{};
  bool logged_once_ = false;
  std::uint64_t held_back_ = 0;
};

}  // namespace sms::gateway
