#pragma once
// Line settings of a tty: raw 8N1 at any bit rate, and the rate currently set. Custom rates
// (128000, 76800, 256000 ...) go through TCSETS2/BOTHER, so every rate of docs/PROTOCOL.md §3 works. On a
// pty master, the rate read is the one the host set on the slave (Linux shares the termios).
#include <cstdint>

namespace sms::simulator {

// Raw 8N1, no flow control, no echo, no line processing, at `baud` bit/s.
// Throws std::system_error naming the fd and the rate.
void configure_raw_serial(int fd, std::uint32_t baud);

// The output bit rate set on the tty behind `fd`; 0 when it holds none (a pty where termios2 is
// missing: tty/termios2_io.h). Throws std::system_error.
std::uint32_t line_speed(int fd);

}  // namespace sms::simulator
