#pragma once
// An RS-485 adapter without echo suppression, played by a relay between two ptys: everything the
// host side (host_path(), where the engine or a tool opens the line) sends goes to the simulator's
// line and straight back to the host, before the servo's answer.
#include <fcntl.h>
#include <poll.h>
#include <stdlib.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <thread>

#include "simulator/serial_line.h"

namespace sms::test {

class EchoingAdapter {
 public:
  // `line` is the simulator's slave path; the engine opens host_path().
  EchoingAdapter(const std::string& line, std::uint32_t baud) {
    host_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (host_ < 0 || ::grantpt(host_) != 0 || ::unlockpt(host_) != 0) throw std::runtime_error("no pty");
    host_path_ = ::ptsname(host_);
    line_ = ::open(line.c_str(), O_RDWR | O_NOCTTY);
    if (line_ < 0) throw std::runtime_error("cannot open " + line);
    simulator::configure_raw_serial(line_, baud);
    relay_ = std::thread([this] { run(); });
  }
  ~EchoingAdapter() {
    stop_ = true;
    relay_.join();
    ::close(line_);
    ::close(host_);
  }
  const std::string& host_path() const { return host_path_; }

 private:
  void run() {
    std::array<std::uint8_t, 512> buffer{};
    while (!stop_) {
      std::array<pollfd, 2> fds{{{host_, POLLIN, 0}, {line_, POLLIN, 0}}};
      if (::poll(fds.data(), fds.size(), 5) <= 0) continue;
      if ((fds[0].revents & POLLIN) != 0) {
        const ssize_t n = ::read(host_, buffer.data(), buffer.size());
        if (n > 0) {
          [[maybe_unused]] const auto echoed = ::write(host_, buffer.data(), static_cast<std::size_t>(n));
          [[maybe_unused]] const auto sent = ::write(line_, buffer.data(), static_cast<std::size_t>(n));
        }
      }
      if ((fds[1].revents & POLLIN) != 0) {
        const ssize_t n = ::read(line_, buffer.data(), buffer.size());
        if (n > 0) [[maybe_unused]]
          const auto passed = ::write(host_, buffer.data(), static_cast<std::size_t>(n));
      }
    }
  }

  int host_ = -1;
  int line_ = -1;
  std::string host_path_;
  std::atomic<bool> stop_{false};
  std::thread relay_;
};

}  // namespace sms::test
