#include "gateway/bus/serial_port.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <ctime>
#include <string>
#include <utility>

#include <spdlog/spdlog.h>

#include "gateway/bus/serial_port_termios2.h"
#include "gateway/bus/wire_monitor.h"

namespace sms::gateway {
namespace {

std::string errno_text(int error) { return std::strerror(error); }

int poll_timeout_ms(std::chrono::nanoseconds timeout) {
  if (timeout <= std::chrono::nanoseconds::zero()) return 0;
  // Round up: poll() counts whole milliseconds and must not return before the deadline.
  const auto ms = std::chrono::ceil<std::chrono::milliseconds>(timeout).count();
  return ms > 60'000 ? 60'000 : static_cast<int>(ms);
}

}  // namespace

unsigned SerialSettings::bits_per_character() const {
  return 1 + 8 + (parity == Parity::None ? 0 : 1) + (stop_bits == 2 ? 2 : 1);
}

std::chrono::nanoseconds wire_time(const SerialSettings& settings, std::size_t characters) {
  if (settings.baud == 0) return std::chrono::nanoseconds::zero();
  const std::uint64_t bits = static_cast<std::uint64_t>(characters) * settings.bits_per_character();
  return std::chrono::nanoseconds((bits * 1'000'000'000ULL + settings.baud - 1) / settings.baud);
}

SerialPort::SerialPort(SerialSettings settings) : settings_(std::move(settings)) {}

SerialPort::~SerialPort() { close(); }

std::string SerialPort::describe_errno(std::string_view action, int error) const {
  const std::string& path = settings_.device;
  std::string text = std::string(action) + " " + path + ": " + errno_text(error);
  switch (error) {
    case ENOENT:
      return text +
             " — the device does not exist: is the adapter plugged in, and is `device` of this bus right? "
             "(ls -l /dev/serial/by-id/ lists the adapters by a name that survives re-plugging)";
    case ENXIO:
    case ENODEV:
      return text +
             " — nothing answers behind this device node (adapter unplugged, or a pty whose other side "
             "closed): plug it in again; the gateway reopens it by itself";
    case EACCES:
    case EPERM:
      return text +
             " — no permission: add the gateway's user to the group owning the device (usually `dialout`: "
             "sudo usermod -aG dialout <user>, then log in again) or run the container with the device mapped";
    case EBUSY:
      return text + " — another program holds the device exclusively: stop it (fuser -v " + path + " shows which)";
    case ENOTTY:
    case EINVAL:
      return text + " — this is not a serial device, or its driver refuses raw mode at " +
             std::to_string(settings_.baud) + " bit/s: point `device` at a tty such as /dev/ttyUSB0";
    default: return text;
  }
}

Expected<Ok> SerialPort::open() {
  close();
  if (settings_.device.empty()) return unexpected(std::string("no serial device configured (`device` is empty)"));
  if (settings_.stop_bits != 1 && settings_.stop_bits != 2) {
    return unexpected("serial device " + settings_.device + ": stop bits must be 1 or 2, not " +
                      std::to_string(settings_.stop_bits));
  }
  const int fd = ::open(settings_.device.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) return unexpected(describe_errno("cannot open serial device", errno));

  // Exclusive: a second gateway (or a terminal program) on the same bus would garble every
  // transaction. Ptys and some drivers refuse it; that is not worth failing for.
  (void)::ioctl(fd, TIOCEXCL);

  if (const int error = detail::configure_raw_line(fd, settings_.baud, settings_.parity, settings_.stop_bits);
      error != 0) {
    ::close(fd);
    return unexpected(describe_errno("cannot set raw " + std::to_string(settings_.baud) + " bit/s " +
                                         std::string(config::to_string(settings_.parity)) + " parity on",
                                     error));
  }
  std::uint32_t actual = 0;
  if (const int error = detail::read_line_speed(fd, actual); error != 0) {
    ::close(fd);
    return unexpected(describe_errno("cannot read back the line settings of", error));
  }
  if (actual == 0) {
    // Only a pseudo-terminal is left without a rate, where termios2 is missing (tty/termios2_io.h).
    spdlog::debug(
        "serial device {} is a pseudo-terminal that holds no bit rate (termios2 is missing: an emulator "
        "such as qemu-user); no wire behind it, so timing goes by the configured {} bit/s",
        settings_.device, settings_.baud);
    actual = settings_.baud;
  }
  ::tcflush(fd, TCIOFLUSH);
  fd_ = fd;
  actual_baud_ = actual;
  return Ok{};
}

void SerialPort::close() {
  if (fd_ < 0) return;
  // Give up exclusivity first: it outlives our descriptor while anyone else holds the tty (a
  // pty's other end, a simulator), and the next open, ours after a restart too, would then fail
  // with EBUSY for a user other than root.
  (void)::ioctl(fd_, TIOCNXCL);
  ::close(fd_);
  fd_ = -1;
}

Expected<std::size_t> SerialPort::discard_input() {
  if (fd_ < 0) return unexpected(settings_.device + " is not open");
  int waiting = 0;
  if (::ioctl(fd_, FIONREAD, &waiting) != 0) waiting = 0;  // only for the counters
  if (::tcflush(fd_, TCIFLUSH) != 0) return unexpected(describe_errno("cannot flush the input of", errno));
  return static_cast<std::size_t>(waiting > 0 ? waiting : 0);
}

Expected<Ok> SerialPort::write_all(std::span<const std::uint8_t> bytes, std::chrono::milliseconds timeout) {
  if (fd_ < 0) return unexpected(settings_.device + " is not open");
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  std::size_t written = 0;
  while (written < bytes.size()) {
    const ssize_t n = ::write(fd_, bytes.data() + written, bytes.size() - written);
    if (n > 0) {
      written += static_cast<std::size_t>(n);
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && errno != EAGAIN) return unexpected(describe_errno("cannot write to", errno));
    // Output queue full (a stalled adapter): wait for room, but not forever.
    const auto left = deadline - std::chrono::steady_clock::now();
    if (left <= std::chrono::steady_clock::duration::zero()) {
      return unexpected("cannot write to " + settings_.device + ": the output queue stayed full for " +
                        std::to_string(timeout.count()) + " ms (adapter stalled?)");
    }
    pollfd entry{fd_, POLLOUT, 0};
    const int ready = ::poll(&entry, 1, poll_timeout_ms(left));
    if (ready < 0 && errno != EINTR) return unexpected(describe_errno("cannot wait for", errno));
    if (ready > 0 && (entry.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) {
      return unexpected(describe_errno("cannot write to", EIO));
    }
  }
  if (monitor_ != nullptr) monitor_->record(WireDirection::ToServos, bytes);
  return Ok{};
}

Expected<Ok> SerialPort::drain() {
  if (fd_ < 0) return unexpected(settings_.device + " is not open");
  while (::tcdrain(fd_) != 0) {
    if (errno != EINTR) return unexpected(describe_errno("cannot drain the output of", errno));
  }
  return Ok{};
}

Expected<std::size_t> SerialPort::read_available(std::span<std::uint8_t> buffer) {
  if (fd_ < 0) return unexpected(settings_.device + " is not open");
  for (;;) {
    const ssize_t n = ::read(fd_, buffer.data(), buffer.size());
    if (n > 0) {
      if (monitor_ != nullptr) monitor_->record(WireDirection::FromServos, buffer.first(static_cast<std::size_t>(n)));
      return static_cast<std::size_t>(n);
    }
    // VMIN is 1, so an empty non-blocking tty says EAGAIN; 0 is a hang-up.
    if (n == 0) return unexpected(describe_errno("lost", ENODEV));
    if (errno == EINTR) continue;
    if (errno == EAGAIN) return std::size_t{0};
    return unexpected(describe_errno("lost", errno));
  }
}

Expected<bool> SerialPort::wait_readable(std::chrono::nanoseconds timeout) {
  if (fd_ < 0) return unexpected(settings_.device + " is not open");
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const int ready = detail::poll_input_until(fd_, deadline);
    if (ready < 0 && errno == EINTR) continue;
    if (ready < 0) return unexpected(describe_errno("cannot wait for", errno));
    // POLLHUP/POLLERR count as readable: the read then reports what went wrong.
    return ready > 0;
  }
}

int detail::poll_input_until(int fd, std::optional<std::chrono::steady_clock::time_point> deadline) {
  pollfd entry{fd, POLLIN, 0};
  if (!deadline) return ::ppoll(&entry, 1, nullptr, nullptr);
  const auto left = std::max<std::chrono::nanoseconds>(*deadline - std::chrono::steady_clock::now(), {});
  const timespec wait{static_cast<time_t>(left.count() / 1'000'000'000),
                      static_cast<long>(left.count() % 1'000'000'000)};
  return ::ppoll(&entry, 1, &wait, nullptr);
}

Expected<Ok> SerialPort::set_baud(std::uint32_t baud) {
  settings_.baud = baud;
  if (fd_ < 0) return Ok{};
  if (const int error = detail::configure_raw_line(fd_, baud, settings_.parity, settings_.stop_bits); error != 0) {
    return unexpected(describe_errno("cannot set the rate of", error));
  }
  actual_baud_ = baud;
  return Ok{};
}

}  // namespace sms::gateway
