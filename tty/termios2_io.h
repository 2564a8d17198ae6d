#pragma once
// Line settings through termios2 (TCGETS2/TCSETS2: any bit rate), falling back to the plain
// termios ioctls (TCGETS/TCSETS: the Bxxx rates only) where termios2 is missing. Linux has had
// termios2 on every architecture since 2.6.20, but qemu-user does not emulate it (7.2 answers
// ENOSYS, 10.0 ENOTTY), and its TCSETS carries the Bxxx codes up to 460800 only (higher ones
// arrive as B0): with the fallback the gateway, sms-sim and the tests run under emulation at
// those rates (docs/ARM.md); any other rate still fails there with termios2's error, checked by
// reading the setting back. (On a real kernel, ENOTTY from TCGETS2 means no tty: TCGETS says so too.)
// One exception: a pseudo-terminal. No wire is behind it and its rate means nothing, so there a
// rate the fallback cannot carry is left out and the rest (raw mode, framing) applied; the pty
// then reads as holding no rate (0 bit/s, B0). A real serial port keeps failing with the error.
// Header-only, for the translation units that include <asm/termbits.h>, never <termios.h> (the
// two cannot be mixed): the gateway's serial port and the simulator's pty. Each returns 0 or errno.
#include <asm/termbits.h>
#include <sys/ioctl.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstdint>

namespace sms::tty {

struct StandardRate {
  std::uint32_t bps;
  tcflag_t code;
};
inline constexpr std::array<StandardRate, 30> kStandardRates{{
    {50, B50},           {75, B75},           {110, B110},         {134, B134},         {150, B150},
    {200, B200},         {300, B300},         {600, B600},         {1200, B1200},       {1800, B1800},
    {2400, B2400},       {4800, B4800},       {9600, B9600},       {19200, B19200},     {38400, B38400},
    {57600, B57600},     {115200, B115200},   {230400, B230400},   {460800, B460800},   {500000, B500000},
    {576000, B576000},   {921600, B921600},   {1000000, B1000000}, {1152000, B1152000}, {1500000, B1500000},
    {2000000, B2000000}, {2500000, B2500000}, {3000000, B3000000}, {3500000, B3500000}, {4000000, B4000000},
}};

// A pseudo-terminal by its device number, which symlinks (sms-sim --link) and bind mounts
// (a container's /dev/ttyUSB0) keep: the pty multiplexer /dev/ptmx (5:2) that masters are opened
// from, and the Unix98 pty slaves (/dev/pts/N: majors 136-143, Documentation/admin-guide/devices.txt).
inline bool is_pseudo_terminal(int fd) {
  struct stat status {};
  if (::fstat(fd, &status) != 0 || !S_ISCHR(status.st_mode)) return false;
  const unsigned int major_number = major(status.st_rdev);
  return (major_number == 5 && minor(status.st_rdev) == 2) || (major_number >= 136 && major_number <= 143);
}

// get() and set() without termios2: the plain ioctls, for the Bxxx rates. A rate without a code
// reads as 0.
inline int get_plain(int fd, termios2& settings) {
  termios plain{};
  if (::ioctl(fd, TCGETS, &plain) != 0) return errno;
  settings = termios2{plain.c_iflag, plain.c_oflag, plain.c_cflag, plain.c_lflag, plain.c_line, {}, 0, 0};
  std::copy(std::begin(plain.c_cc), std::end(plain.c_cc), std::begin(settings.c_cc));
  for (const StandardRate& rate : kStandardRates) {
    if (rate.code == (plain.c_cflag & CBAUD)) settings.c_ispeed = settings.c_ospeed = rate.bps;
  }
  return 0;
}

// `termios2_error` is what TCSETS2 answered; it is returned for a rate this path cannot carry,
// except on a pseudo-terminal (see the top of this file).
inline int set_plain(int fd, const termios2& settings, int termios2_error) {
  const auto* rate = std::find_if(kStandardRates.begin(), kStandardRates.end(),
                                  [&](const StandardRate& standard) { return standard.bps == settings.c_ospeed; });
  const bool pty = is_pseudo_terminal(fd);
  if (rate == kStandardRates.end() && !pty) return termios2_error;
  const tcflag_t code = rate == kStandardRates.end() ? static_cast<tcflag_t>(B0) : rate->code;
  // One rate for both directions (input speed bits 0), as the termios2 settings ask.
  termios plain{settings.c_iflag,
                settings.c_oflag,
                (settings.c_cflag & ~static_cast<tcflag_t>(CBAUD | (CBAUD << IBSHIFT))) | code,
                settings.c_lflag,
                settings.c_line,
                {}};
  std::copy(std::begin(settings.c_cc), std::end(settings.c_cc), std::begin(plain.c_cc));
  if (::ioctl(fd, TCSETS, &plain) != 0) return errno;
  termios held{};
  if (::ioctl(fd, TCGETS, &held) != 0) return errno;
  return (held.c_cflag & CBAUD) == code || pty ? 0 : termios2_error;
}

inline int get(int fd, termios2& settings) {
  if (::ioctl(fd, TCGETS2, &settings) == 0) return 0;
  if (errno != ENOSYS && errno != ENOTTY) return errno;
  return get_plain(fd, settings);
}

inline int set(int fd, const termios2& settings) {
  if (::ioctl(fd, TCSETS2, &settings) == 0) return 0;
  const int termios2_error = errno;
  if (termios2_error != ENOSYS && termios2_error != ENOTTY) return termios2_error;
  return set_plain(fd, settings, termios2_error);
}

}  // namespace sms::tty
