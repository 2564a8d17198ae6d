#include "gateway/bus/wakeup.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <ctime>
#include <system_error>

namespace sms::gateway {

Wakeup::Wakeup() : fd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {
  if (fd_ < 0) throw std::system_error(errno, std::generic_category(), "eventfd for a bus thread");
}

Wakeup::~Wakeup() { ::close(fd_); }

void Wakeup::notify() {
  const std::uint64_t one = 1;
  // EAGAIN only when the counter is full: the sleeper is woken anyway.
  while (::write(fd_, &one, sizeof one) < 0 && errno == EINTR) {
  }
}

void Wakeup::wait(std::optional<std::chrono::steady_clock::time_point> deadline) {
  pollfd entry{fd_, POLLIN, 0};
  timespec timeout{};
  timespec* wait_for = nullptr;
  if (deadline) {
    const auto left = std::max<std::chrono::nanoseconds>(*deadline - std::chrono::steady_clock::now(), {});
    timeout = {static_cast<time_t>(left.count() / 1'000'000'000), static_cast<long>(left.count() % 1'000'000'000)};
    wait_for = &timeout;
  }
  if (::ppoll(&entry, 1, wait_for, nullptr) > 0) {
    std::uint64_t count = 0;
    (void)::read(fd_, &count, sizeof count);  // consumes every notify() so far
  }
}

}  // namespace sms::gateway
