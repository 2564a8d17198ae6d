#pragma once
// A serial line to a servo bus: a tty (USB/RS-485 adapter, or a pty slave such as the
// simulator's) in raw mode at any bit rate of the protocols' baud tables (docs/PROTOCOL.md §3) —
// 76 800, 128 000, 256 000 … are set with termios2/BOTHER. The descriptor is non-blocking;
// the bus transactor waits for readiness with poll and reads what is there.
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "config/config.h"
#include "protocol/expected.h"

namespace sms::gateway {

class WireMonitor;
using config::Parity;

struct SerialSettings {
  std::string device;  // /dev/ttyUSB0, /dev/serial/by-id/..., a pty slave path
  std::uint32_t baud = 1'000'000;
  Parity parity = Parity::None;  // the servos use 8N1 (docs/PROTOCOL.md §1); adapters in between may not
  std::uint8_t stop_bits = 1;    // 1 or 2

  // Start bit, 8 data bits, parity bit if any, stop bits.
  unsigned bits_per_character() const;
};

// Time `characters` bytes occupy the line at the settings' rate (docs/PROTOCOL.md §5), rounded up.
std::chrono::nanoseconds wire_time(const SerialSettings& settings, std::size_t characters);

namespace detail {
// ppoll() for input on one descriptor until `deadline` (nullopt: none), to the nanosecond (poll()
// would round a reply deadline a millisecond or two away up to whole milliseconds). Returns
// ppoll's result: > 0 readable (or failed: the read says why), 0 at the deadline, < 0 errno.
int poll_input_until(int fd, std::optional<std::chrono::steady_clock::time_point> deadline);
}  // namespace detail

class SerialPort {
 public:
  explicit SerialPort(SerialSettings settings);
  ~SerialPort();
  SerialPort(const SerialPort&) = delete;
  SerialPort& operator=(const SerialPort&) = delete;

  // Opens the device non-blocking and exclusive, raw, at the configured rate. The error names
  // the device, what failed and what to do (plug the adapter in, fix `device`, join `dialout`).
  Expected<Ok> open();
  void close();
  bool is_open() const { return fd_ >= 0; }
  int native_handle() const { return fd_; }
  const SerialSettings& settings() const { return settings_; }
  // The rate the driver reports after open(); a real adapter may round an exotic rate.
  std::uint32_t actual_baud() const { return actual_baud_; }

  // Throws away whatever arrived and was not read: late replies, echoes, noise. The host does
  // this before each transmit (docs/PROTOCOL.md §1.1, host practice). Returns how many bytes it dropped.
  Expected<std::size_t> discard_input();
  // Writes every byte; waits for room in the output queue up to `timeout`.
  Expected<Ok> write_all(std::span<const std::uint8_t> bytes, std::chrono::milliseconds timeout);
  // Returns once the driver has sent everything written (tcdrain).
  Expected<Ok> drain();
  // What is available now, without blocking: 0 when nothing is. An error means the device is
  // gone (unplugged adapter, EIO, a pty whose master closed): close and reopen later.
  Expected<std::size_t> read_available(std::span<std::uint8_t> buffer);
  // Waits up to `timeout` (to the microsecond) for bytes to read (or for the device to fail).
  // False on timeout.
  Expected<bool> wait_readable(std::chrono::nanoseconds timeout);
  // Changes the rate: on the open descriptor at once (a reopen could meet EBUSY while someone
  // else holds the tty), else for the next open().
  Expected<Ok> set_baud(std::uint32_t baud);
  // The bus monitor's tap (wire_monitor.h): what write_all() sends and read_available() reads is
  // also recorded there. nullptr: nothing is recorded. Set before the bus thread starts.
  void set_monitor(WireMonitor* monitor) { monitor_ = monitor; }

 private:
  std::string describe_errno(std::string_view action, int error) const;

  SerialSettings settings_;
  int fd_ = -1;
  std::uint32_t actual_baud_ = 0;
  WireMonitor* monitor_ = nullptr;
};

}  // namespace sms::gateway
