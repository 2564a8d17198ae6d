// <asm/termbits.h> for termios2 (custom rates); it cannot share a TU with <termios.h>.
#include "tests/simulator/host_port.h"

#include <asm/termbits.h>
#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <stdexcept>
#include <system_error>

#include "protocol/stream_decoder.h"

namespace sms::simulator::testing {

HostPort::HostPort(const std::string& path, std::uint32_t baud) {
  fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) throw std::system_error(errno, std::generic_category(), "test host cannot open " + path);
  set_baud(baud);
}

HostPort::~HostPort() {
  if (fd_ >= 0) ::close(fd_);
}

void HostPort::set_baud(std::uint32_t baud) {
  termios2 tio{};
  if (ioctl(fd_, TCGETS2, &tio) != 0) throw std::system_error(errno, std::generic_category(), "TCGETS2");
  tio.c_iflag = 0;
  tio.c_oflag = 0;
  tio.c_lflag = 0;
  tio.c_cflag = CS8 | CREAD | CLOCAL | BOTHER | (BOTHER << IBSHIFT);
  tio.c_ispeed = baud;
  tio.c_ospeed = baud;
  tio.c_cc[VMIN] = 0;
  tio.c_cc[VTIME] = 0;
  if (ioctl(fd_, TCSETS2, &tio) != 0) throw std::system_error(errno, std::generic_category(), "TCSETS2");
}

void HostPort::send(const Bytes& bytes) {
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t written = ::write(fd_, bytes.data() + done, bytes.size() - done);
    if (written < 0) {
      if (errno == EAGAIN) continue;
      throw std::system_error(errno, std::generic_category(), "test host write");
    }
    done += static_cast<std::size_t>(written);
  }
}

Bytes HostPort::receive(std::chrono::milliseconds quiet, std::chrono::milliseconds limit) {
  Bytes bytes;
  const auto give_up = std::chrono::steady_clock::now() + limit;
  for (;;) {
    const auto now = std::chrono::steady_clock::now();
    if (now >= give_up) return bytes;
    const auto wait =
        bytes.empty() ? give_up - now : std::min<std::chrono::steady_clock::duration>(quiet, give_up - now);
    pollfd pfd{fd_, POLLIN, 0};
    const int ready =
        ::poll(&pfd, 1, static_cast<int>(std::chrono::duration_cast<std::chrono::milliseconds>(wait).count()) + 1);
    if (ready <= 0) {
      if (!bytes.empty()) return bytes;
      continue;
    }
    std::uint8_t buffer[512];
    const ssize_t got = ::read(fd_, buffer, sizeof buffer);
    if (got > 0) bytes.insert(bytes.end(), buffer, buffer + got);
  }
}

Bytes HostPort::receive_exactly(std::size_t count, std::chrono::milliseconds limit) {
  Bytes bytes;
  const auto give_up = std::chrono::steady_clock::now() + limit;
  while (bytes.size() < count) {
    const auto now = std::chrono::steady_clock::now();
    if (now >= give_up) break;
    pollfd pfd{fd_, POLLIN, 0};
    const auto wait = std::chrono::duration_cast<std::chrono::milliseconds>(give_up - now).count() + 1;
    if (::poll(&pfd, 1, static_cast<int>(wait)) <= 0) continue;
    std::uint8_t buffer[512];
    const ssize_t got = ::read(fd_, buffer, std::min(sizeof buffer, count - bytes.size()));
    if (got > 0) bytes.insert(bytes.end(), buffer, buffer + got);
  }
  return bytes;
}

Bytes HostPort::receive_answer(std::size_t count, std::chrono::milliseconds limit, std::chrono::milliseconds quiet) {
  Bytes bytes = receive_exactly(count, limit);
  if (bytes.size() < count) return bytes;
  const Bytes after = receive(quiet, quiet);
  bytes.insert(bytes.end(), after.begin(), after.end());
  return bytes;
}

std::optional<protocol::Packet> HostPort::transact(const protocol::PacketFormat& format,
                                                   const protocol::Packet& request, std::chrono::milliseconds limit) {
  send(protocol::encode(format, request));
  protocol::StreamDecoder decoder(format);
  const auto give_up = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < give_up) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(give_up - std::chrono::steady_clock::now());
    const Bytes bytes = receive(5ms, std::max(left, 1ms));
    decoder.feed(bytes);
    while (const auto event = decoder.next()) {
      if (event->kind == protocol::DecodeEvent::Kind::Frame) return event->packet;
    }
  }
  return std::nullopt;
}

std::vector<protocol::Packet> HostPort::transact_all(const protocol::PacketFormat& format,
                                                     const protocol::Packet& request, std::chrono::milliseconds quiet) {
  send(protocol::encode(format, request));
  // Silence is the expected answer often enough: do not wait long for a first byte either.
  return decode_all(format, receive(quiet, quiet + std::chrono::milliseconds(60)));
}

std::vector<protocol::Packet> HostPort::transact_expecting(const protocol::PacketFormat& format,
                                                           const protocol::Packet& request, std::size_t count,
                                                           std::chrono::milliseconds limit,
                                                           std::chrono::milliseconds quiet) {
  send(protocol::encode(format, request));
  protocol::StreamDecoder decoder(format);
  std::vector<protocol::Packet> packets;
  const auto give_up = std::chrono::steady_clock::now() + limit;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(give_up - std::chrono::steady_clock::now());
    // Until `count` frames: a little at a time up to the limit; then only while more follow.
    const Bytes bytes = packets.size() < count ? receive(5ms, std::max(left, 1ms)) : receive(quiet, quiet);
    decoder.feed(bytes);
    while (const auto event = decoder.next()) {
      if (event->kind == protocol::DecodeEvent::Kind::Frame) packets.push_back(event->packet);
    }
    if (packets.size() >= count ? bytes.empty() : std::chrono::steady_clock::now() >= give_up) return packets;
  }
}

std::vector<protocol::Packet> decode_all(const protocol::PacketFormat& format, const Bytes& bytes) {
  protocol::StreamDecoder decoder(format);
  decoder.feed(bytes);
  std::vector<protocol::Packet> packets;
  while (const auto event = decoder.next()) {
    if (event->kind == protocol::DecodeEvent::Kind::Frame) packets.push_back(event->packet);
  }
  return packets;
}

std::string hex(const Bytes& bytes) {
  std::string text;
  char digits[4];
  for (const std::uint8_t byte : bytes) {
    std::snprintf(digits, sizeof digits, "%02X ", byte);
    text += digits;
  }
  if (!text.empty()) text.pop_back();
  return text;
}

}  // namespace sms::simulator::testing
