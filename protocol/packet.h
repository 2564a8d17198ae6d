#pragma once
// The packet shape shared by the Feetech `FF FF` and the `D5 5D` protocols (docs/PROTOCOL.md §1.1, §1.2):
//   HEADER(2) | ID | LEN | CODE | P1..PN | CHK      LEN = N + 2
// CODE is the instruction in a request and the ERROR byte in a status reply. The two
// protocols differ only in header bytes and checksum (inverted sum vs plain sum), so
// one encoder and one decoder serve both, parameterised by PacketFormat.
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

namespace sms::protocol {

using Bytes = std::vector<std::uint8_t>;

struct PacketFormat {
  std::string_view name;
  std::array<std::uint8_t, 2> header;
  bool inverted_checksum;  // feetech: ~sum; d55d: plain sum
};

inline constexpr PacketFormat kFeetechFormat{"feetech", {0xFF, 0xFF}, true};
inline constexpr PacketFormat kD55dFormat{"d55d", {0xD5, 0x5D}, false};

inline constexpr std::uint8_t kBroadcastId = 0xFE;
// LEN is one byte and counts CODE + params + CHK: at most 253 parameter bytes.
inline constexpr std::size_t kMaxParams = 253;
// Smallest frame: header(2) id len code chk.
inline constexpr std::size_t kMinFrameSize = 6;

struct Packet {
  std::uint8_t id = 0;
  std::uint8_t code = 0;  // instruction (request) or ERROR byte (status)
  Bytes params;

  friend bool operator==(const Packet&, const Packet&) = default;
};

// Checksum over ID, LEN, CODE and params (everything between header and CHK).
std::uint8_t checksum(const PacketFormat& format, std::span<const std::uint8_t> body);

// Whole frame, header to checksum. Throws std::length_error past kMaxParams.
Bytes encode(const PacketFormat& format, const Packet& packet);

}  // namespace sms::protocol
