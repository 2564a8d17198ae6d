#pragma once
// The host side of a test: opens a simulator's pty slave like a serial port, sets its line
// speed (its own termios2 code, not the simulator's), and speaks with the foundation codecs.
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "protocol/modbus_rtu.h"
#include "protocol/packet.h"

namespace sms::simulator::testing {

using protocol::Bytes;
using namespace std::chrono_literals;

class HostPort {
 public:
  HostPort(const std::string& path, std::uint32_t baud);
  ~HostPort();
  HostPort(const HostPort&) = delete;
  HostPort& operator=(const HostPort&) = delete;

  void set_baud(std::uint32_t baud);
  int fd() const { return fd_; }

  void send(const Bytes& bytes);
  // Whatever arrives until the line stays quiet for `quiet` (or `limit` passes).
  Bytes receive(std::chrono::milliseconds quiet = 30ms, std::chrono::milliseconds limit = 1000ms);
  // Exactly `count` bytes, or fewer if `limit` passes first (an answer's bytes: awaited as long
  // as a loaded machine holds the simulator back).
  Bytes receive_exactly(std::size_t count, std::chrono::milliseconds limit = 5000ms);
  // An answer of `count` bytes, awaited as long as a loaded machine holds the simulator back (at
  // most `limit`), and whatever follows it until the line stays quiet for `quiet`: a test of what
  // was answered, never of how soon (tests/README.md "Counting on a loaded machine").
  Bytes receive_answer(std::size_t count, std::chrono::milliseconds limit = 5000ms,
                       std::chrono::milliseconds quiet = 30ms);

  // Sends the packet and decodes the first status frame that comes back, awaited up to `limit`
  // (a test that expects silence passes its own, short one).
  std::optional<protocol::Packet> transact(const protocol::PacketFormat& format, const protocol::Packet& request,
                                           std::chrono::milliseconds limit = 5000ms);
  // Every status frame until the line goes quiet: for a request whose answer is silence.
  std::vector<protocol::Packet> transact_all(const protocol::PacketFormat& format, const protocol::Packet& request,
                                             std::chrono::milliseconds quiet = 40ms);
  // Every status frame until `count` have come (or `limit` passes), and any that follow within
  // `quiet`: for a request that is answered, awaited as long as a loaded machine holds the
  // simulator back, not for a window (tests/README.md "Counting on a loaded machine").
  std::vector<protocol::Packet> transact_expecting(const protocol::PacketFormat& format,
                                                   const protocol::Packet& request, std::size_t count,
                                                   std::chrono::milliseconds limit = 5000ms,
                                                   std::chrono::milliseconds quiet = 40ms);

 private:
  int fd_ = -1;
};

// Decodes every whole frame in `bytes`.
std::vector<protocol::Packet> decode_all(const protocol::PacketFormat& format, const Bytes& bytes);
// "FF FF 01 02 00 FC" for failure messages.
std::string hex(const Bytes& bytes);

}  // namespace sms::simulator::testing
