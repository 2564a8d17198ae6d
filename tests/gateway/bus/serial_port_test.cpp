// SerialPort on a real pty: raw mode at exotic rates, flushing, loss of the other side, and
// the errors an integration engineer sees for a wrong `device`.
#include "gateway/bus/serial_port.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "simulator/serial_line.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

// The host side of a pty pair: the test plays the wire behind the port.
class PtyPair {
 public:
  PtyPair() {
    master_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (master_ < 0 || ::grantpt(master_) != 0 || ::unlockpt(master_) != 0) throw std::runtime_error("no pty");
    slave_path_ = ::ptsname(master_);
  }
  ~PtyPair() { close_master(); }
  PtyPair(const PtyPair&) = delete;
  PtyPair& operator=(const PtyPair&) = delete;

  int master() const { return master_; }
  const std::string& slave_path() const { return slave_path_; }
  void close_master() {
    if (master_ >= 0) ::close(master_);
    master_ = -1;
  }
  void send(std::vector<std::uint8_t> bytes) const {
    ASSERT_EQ(::write(master_, bytes.data(), bytes.size()), static_cast<ssize_t>(bytes.size()));
  }
  std::vector<std::uint8_t> receive(std::size_t count) const {
    std::vector<std::uint8_t> bytes(count);
    std::size_t got = 0;
    while (got < count) {
      const ssize_t n = ::read(master_, bytes.data() + got, count - got);
      if (n <= 0) break;
      got += static_cast<std::size_t>(n);
    }
    bytes.resize(got);
    return bytes;
  }

 private:
  int master_ = -1;
  std::string slave_path_;
};

SerialSettings settings_for(std::string device, std::uint32_t baud) {
  SerialSettings settings;
  settings.device = std::move(device);
  settings.baud = baud;
  return settings;
}

TEST(SerialPort, OpensAPtyAtRatesOutsideTheBxxxConstants) {
  for (const std::uint32_t baud : {76'800U, 128'000U, 256'000U, 1'000'000U, 1'792'000U}) {
    PtyPair pty;
    SerialPort port(settings_for(pty.slave_path(), baud));
    const auto opened = port.open();
    ASSERT_TRUE(opened) << opened.error();
    EXPECT_EQ(port.actual_baud(), baud);
    // The other side of the line sees the same rate (Linux shares the pty's termios).
    EXPECT_EQ(simulator::line_speed(pty.master()), baud);
  }
}

TEST(SerialPort, WritesAndReadsRawBytesWithoutLineProcessing) {
  PtyPair pty;
  SerialPort port(settings_for(pty.slave_path(), 1'000'000));
  const auto opened = port.open();
  ASSERT_TRUE(opened) << opened.error();
  // CR, LF, XON/XOFF and 0xFF must pass untouched: raw mode.
  const std::vector<std::uint8_t> frame{0xFF, 0xFF, 0x01, 0x0D, 0x0A, 0x11, 0x13, 0x00};
  ASSERT_TRUE(port.write_all(frame, 100ms));
  EXPECT_EQ(pty.receive(frame.size()), frame);

  pty.send({0x0D, 0x0A, 0x03, 0x1C});
  ASSERT_TRUE(*port.wait_readable(1s));
  std::array<std::uint8_t, 16> buffer{};
  const auto got = port.read_available(buffer);
  ASSERT_TRUE(got) << got.error();
  ASSERT_EQ(*got, 4U);
  EXPECT_EQ(std::vector<std::uint8_t>(buffer.begin(), buffer.begin() + 4),
            (std::vector<std::uint8_t>{0x0D, 0x0A, 0x03, 0x1C}));
}

TEST(SerialPort, ReadWithNothingWaitingReturnsZeroAtOnce) {
  PtyPair pty;
  SerialPort port(settings_for(pty.slave_path(), 115'200));
  const auto opened = port.open();
  ASSERT_TRUE(opened) << opened.error();
  std::array<std::uint8_t, 8> buffer{};
  const auto got = port.read_available(buffer);
  ASSERT_TRUE(got) << got.error();
  EXPECT_EQ(*got, 0U);
  EXPECT_FALSE(*port.wait_readable(5ms));
}

TEST(SerialPort, DiscardInputDropsWhatWasNotReadAndSaysHowMuch) {
  PtyPair pty;
  SerialPort port(settings_for(pty.slave_path(), 1'000'000));
  const auto opened = port.open();
  ASSERT_TRUE(opened) << opened.error();
  pty.send({0xAA, 0xBB, 0xCC});
  ASSERT_TRUE(*port.wait_readable(1s));
  const auto dropped = port.discard_input();
  ASSERT_TRUE(dropped) << dropped.error();
  EXPECT_EQ(*dropped, 3U);
  std::array<std::uint8_t, 8> buffer{};
  EXPECT_EQ(*port.read_available(buffer), 0U);
}

TEST(SerialPort, ReadReportsTheDeviceGoneWhenThePtyMasterCloses) {
  PtyPair pty;
  SerialPort port(settings_for(pty.slave_path(), 1'000'000));
  const auto opened = port.open();
  ASSERT_TRUE(opened) << opened.error();
  pty.close_master();
  ASSERT_TRUE(*port.wait_readable(1s));  // a hang-up is readable
  std::array<std::uint8_t, 8> buffer{};
  const auto got = port.read_available(buffer);
  ASSERT_FALSE(got);
  EXPECT_NE(got.error().find(pty.slave_path()), std::string::npos) << got.error();
}

TEST(SerialPort, MissingDeviceErrorNamesThePathAndWhatToCheck) {
  SerialPort port(settings_for("/dev/ttyUSB-sms-gateway-missing", 1'000'000));
  const auto opened = port.open();
  ASSERT_FALSE(opened);
  EXPECT_NE(opened.error().find("/dev/ttyUSB-sms-gateway-missing"), std::string::npos) << opened.error();
  EXPECT_NE(opened.error().find("does not exist"), std::string::npos) << opened.error();
  EXPECT_NE(opened.error().find("/dev/serial/by-id/"), std::string::npos) << opened.error();
  EXPECT_FALSE(port.is_open());
}

TEST(SerialPort, RegularFileIsRejectedAsNotASerialDevice) {
  char path[] = "/tmp/sms-gateway-not-a-tty-XXXXXX";
  const int fd = ::mkstemp(path);
  ASSERT_GE(fd, 0);
  ::close(fd);
  SerialPort port(settings_for(path, 1'000'000));
  const auto opened = port.open();
  ::unlink(path);
  ASSERT_FALSE(opened);
  EXPECT_NE(opened.error().find("not a serial device"), std::string::npos) << opened.error();
  EXPECT_NE(opened.error().find(path), std::string::npos) << opened.error();
}

TEST(SerialPort, StopBitsOtherThanOneOrTwoAreRefused) {
  PtyPair pty;
  SerialSettings settings = settings_for(pty.slave_path(), 1'000'000);
  settings.stop_bits = 3;
  SerialPort port(settings);
  const auto opened = port.open();
  ASSERT_FALSE(opened);
  EXPECT_NE(opened.error().find("stop bits must be 1 or 2"), std::string::npos) << opened.error();
}

TEST(SerialPort, WireTimeCountsStartParityAndStopBits) {
  SerialSettings settings = settings_for("x", 1'000'000);
  EXPECT_EQ(settings.bits_per_character(), 10U);
  EXPECT_EQ(wire_time(settings, 8), 80us);  // docs/PROTOCOL.md §5: 10 bits a character at 1 Mbaud
  settings.parity = Parity::Even;
  settings.stop_bits = 2;
  EXPECT_EQ(settings.bits_per_character(), 12U);
  settings.baud = 76'800;
  settings.parity = Parity::None;
  settings.stop_bits = 1;
  // 21 bytes at 76 800 bit/s: 210 bits / 76 800 bit/s = 2 734 375 ns.
  EXPECT_EQ(wire_time(settings, 21), std::chrono::nanoseconds(2'734'375));
}

}  // namespace
}  // namespace sms::gateway
