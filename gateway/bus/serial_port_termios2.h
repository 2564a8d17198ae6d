#pragma once
// Line settings through termios2 (TCGETS2/TCSETS2 with BOTHER), so any bit rate works, not
// only the Bxxx constants. Kept in its own translation unit: <asm/termbits.h> redefines what
// <termios.h> declares, and the two cannot be included together.
#include <cstdint>

namespace sms::config {
enum class Parity : std::uint8_t;  // defined in config/config.h; declared only, to keep this header light
}

namespace sms::gateway::detail {

// Raw mode (no echo, no line editing, no flow control, no CR/LF mapping), 8 data bits,
// receiver on, modem lines ignored, VMIN 1 / VTIME 0. Returns 0 or the errno of the ioctl.
int configure_raw_line(int fd, std::uint32_t baud, config::Parity parity, std::uint8_t stop_bits);

// The output rate the driver holds now; 0 for a pseudo-terminal left without one where termios2
// is missing (tty/termios2_io.h). Returns 0 or the errno of the ioctl.
int read_line_speed(int fd, std::uint32_t& baud);

}  // namespace sms::gateway::detail
