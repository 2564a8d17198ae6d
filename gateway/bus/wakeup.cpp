#include "gateway/bus/wakeup.h"

#include <sys/eventfd.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <system_error>

#include "gateway/bus/serial_port.h"

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
  // An EINTR simply returns: every caller waits in a loop that looks at its state again.
  if (detail::poll_input_until(fd_, deadline) > 0) {
    // Consumes every notify() so far. A failed read (EINTR, or EAGAIN when another waiter took
    // the count) leaves nothing to do: the caller looks at its state again either way.
    std::uint64_t count = 0;
    if (::read(fd_, &count, sizeof count) < 0) return;
  }
}

}  // namespace sms::gateway
