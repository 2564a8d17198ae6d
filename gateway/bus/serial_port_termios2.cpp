// Only <asm/termbits.h> here, never <termios.h> (see the header).
#include "gateway/bus/serial_port_termios2.h"

#include <cerrno>

#include "config/config.h"
#include "tty/termios2_io.h"

namespace sms::gateway::detail {

int configure_raw_line(int fd, std::uint32_t baud, config::Parity parity, std::uint8_t stop_bits) {
  termios2 settings{};
  if (const int error = tty::get(fd, settings); error != 0) return error;
  settings.c_iflag &= ~static_cast<tcflag_t>(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF |
                                             IXANY | INPCK | IGNPAR);
  settings.c_oflag &= ~static_cast<tcflag_t>(OPOST);
  settings.c_lflag &= ~static_cast<tcflag_t>(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
  settings.c_cflag &= ~static_cast<tcflag_t>(CSIZE | PARENB | PARODD | CSTOPB | CRTSCTS | CBAUD | (CBAUD << IBSHIFT));
  settings.c_cflag |= CS8 | CREAD | CLOCAL | BOTHER | (BOTHER << IBSHIFT);
  if (parity != config::Parity::None) {
    settings.c_cflag |= PARENB;
    if (parity == config::Parity::Odd) settings.c_cflag |= PARODD;
    // Drop characters with a parity error: the packet checksum then fails and the decoder
    // resynchronises, as for any other damaged frame.
    settings.c_iflag |= INPCK | IGNPAR;
  }
  if (stop_bits == 2) settings.c_cflag |= CSTOPB;
  settings.c_ispeed = baud;
  settings.c_ospeed = baud;
  settings.c_cc[VMIN] = 1;
  settings.c_cc[VTIME] = 0;
  return tty::set(fd, settings);
}

int read_line_speed(int fd, std::uint32_t& baud) {
  termios2 settings{};
  if (const int error = tty::get(fd, settings); error != 0) return error;
  baud = settings.c_ospeed;
  return 0;
}

}  // namespace sms::gateway::detail
