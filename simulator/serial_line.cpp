// <asm/termbits.h> gives termios2/BOTHER; it cannot be mixed with <termios.h> in one TU.
#include "simulator/serial_line.h"

#include <asm/termbits.h>
#include <sys/ioctl.h>

#include "tty/termios2_io.h"  // header-only: termios2 with the fallback qemu-user needs

#include <cerrno>
#include <string>
#include <system_error>

namespace sms::simulator {
namespace {

termios2 get_termios(int fd) {
  termios2 settings{};
  if (const int error = tty::get(fd, settings); error != 0) {
    throw std::system_error(error, std::generic_category(),
                            "cannot read the line settings of fd " + std::to_string(fd) + " (is it a tty?)");
  }
  return settings;
}

}  // namespace

void configure_raw_serial(int fd, std::uint32_t baud) {
  termios2 settings = get_termios(fd);
  settings.c_iflag &=
      ~static_cast<tcflag_t>(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF | IXANY | INPCK);
  settings.c_oflag &= ~static_cast<tcflag_t>(OPOST);
  settings.c_lflag &= ~static_cast<tcflag_t>(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
  settings.c_cflag &= ~static_cast<tcflag_t>(CSIZE | PARENB | CSTOPB | CRTSCTS | CBAUD | (CBAUD << IBSHIFT));
  settings.c_cflag |= CS8 | CREAD | CLOCAL | BOTHER | (BOTHER << IBSHIFT);
  settings.c_ispeed = baud;
  settings.c_ospeed = baud;
  settings.c_cc[VMIN] = 1;
  settings.c_cc[VTIME] = 0;
  if (const int error = tty::set(fd, settings); error != 0) {
    throw std::system_error(
        error, std::generic_category(),
        "cannot set fd " + std::to_string(fd) + " to raw 8N1 at " + std::to_string(baud) + " bit/s");
  }
}

std::uint32_t line_speed(int fd) { return get_termios(fd).c_ospeed; }

}  // namespace sms::simulator
