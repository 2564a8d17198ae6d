// tty/termios2_io.h: how a pseudo-terminal is told from other files, and the path without
// termios2 (what runs under qemu-user) on this kernel's ptys: a Bxxx rate is carried, a rate
// without a code leaves a pty raw and without a rate, and anything else keeps the error.
// Only <asm/termbits.h> in this file, never <termios.h> (see the header).
#include "tty/termios2_io.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <string>

namespace sms::tty {
namespace {

class Pty {
 public:
  Pty() {
    master_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (master_ < 0 || ::grantpt(master_) != 0 || ::unlockpt(master_) != 0) throw std::runtime_error("no pty");
    slave_ = ::open(::ptsname(master_), O_RDWR | O_NOCTTY);
    if (slave_ < 0) throw std::runtime_error("cannot open the pty slave");
  }
  ~Pty() {
    ::close(slave_);
    ::close(master_);
  }
  Pty(const Pty&) = delete;
  Pty& operator=(const Pty&) = delete;

  int master() const { return master_; }
  int slave() const { return slave_; }

 private:
  int master_ = -1;
  int slave_ = -1;
};

class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }

 private:
  int fd_;
};

// What the gateway's serial port asks for: raw 8N1 at `baud` (gateway/bus/serial_port_termios2.cpp).
termios2 raw_request(int fd, std::uint32_t baud) {
  termios2 settings{};
  if (get_plain(fd, settings) != 0) throw std::runtime_error("TCGETS failed on fd " + std::to_string(fd));
  settings.c_lflag &= ~static_cast<tcflag_t>(ECHO | ICANON | ISIG | IEXTEN);
  settings.c_cflag &= ~static_cast<tcflag_t>(CSIZE | PARENB | CBAUD | (CBAUD << IBSHIFT));
  settings.c_cflag |= CS8 | CREAD | CLOCAL | BOTHER | (BOTHER << IBSHIFT);
  settings.c_ispeed = settings.c_ospeed = baud;
  return settings;
}

TEST(Termios2Io, TellsPseudoTerminalsByTheirDeviceNumber) {
  const Pty pty;
  EXPECT_TRUE(is_pseudo_terminal(pty.master()));
  EXPECT_TRUE(is_pseudo_terminal(pty.slave()));

  const Fd null(::open("/dev/null", O_RDWR | O_CLOEXEC));  // a character device too (1:3)
  ASSERT_GE(null.get(), 0);
  EXPECT_FALSE(is_pseudo_terminal(null.get()));
  int pipe_fds[2];
  ASSERT_EQ(::pipe(pipe_fds), 0);
  const Fd read_end(pipe_fds[0]);
  const Fd write_end(pipe_fds[1]);
  EXPECT_FALSE(is_pseudo_terminal(read_end.get()));
  std::FILE* file = std::tmpfile();
  ASSERT_NE(file, nullptr);
  EXPECT_FALSE(is_pseudo_terminal(::fileno(file)));
  std::fclose(file);
  EXPECT_FALSE(is_pseudo_terminal(-1));
}

TEST(Termios2Io, WithoutTermios2APtyTakesARateThatHasABxxxCode) {
  const Pty pty;
  ASSERT_EQ(set_plain(pty.slave(), raw_request(pty.slave(), 115'200), ENOSYS), 0);
  termios2 held{};
  ASSERT_EQ(get_plain(pty.master(), held), 0);
  EXPECT_EQ(held.c_ospeed, 115'200U);
  EXPECT_EQ(held.c_lflag & ICANON, 0U);
}

TEST(Termios2Io, WithoutTermios2APtyIsLeftRawAndWithoutARateItCannotCarry) {
  for (const std::uint32_t baud : {76'800U, 128'000U, 256'000U}) {
    const Pty pty;
    ASSERT_EQ(set_plain(pty.slave(), raw_request(pty.slave(), baud), ENOSYS), 0) << baud;
    termios2 held{};
    ASSERT_EQ(get_plain(pty.master(), held), 0);
    EXPECT_EQ(held.c_ospeed, 0U) << baud << " bit/s: the pty reads as holding no rate";
    EXPECT_EQ(held.c_cflag & CBAUD, static_cast<tcflag_t>(B0));
    EXPECT_EQ(held.c_lflag & (ICANON | ECHO), 0U) << "raw mode applied all the same";
    EXPECT_EQ(held.c_cflag & CSIZE, static_cast<tcflag_t>(CS8));
  }
}

TEST(Termios2Io, WithoutTermios2AnythingButAPtyKeepsTheError) {
  const Fd null(::open("/dev/null", O_RDWR | O_CLOEXEC));
  ASSERT_GE(null.get(), 0);
  termios2 request{};
  request.c_cflag = CS8 | CREAD | CLOCAL | BOTHER;
  // A rate without a Bxxx code: termios2's own error, as a real serial port would give it.
  request.c_ispeed = request.c_ospeed = 128'000;
  EXPECT_EQ(set_plain(null.get(), request, ENOSYS), ENOSYS);
  // A rate with a code: the plain ioctl's own answer.
  request.c_ispeed = request.c_ospeed = 115'200;
  EXPECT_EQ(set_plain(null.get(), request, ENOSYS), ENOTTY);
}

}  // namespace
}  // namespace sms::tty
