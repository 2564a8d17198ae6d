#pragma once
// Incremental, I/O-free decoder for PacketFormat frames: feed it whatever bytes arrived,
// in any chunking, and pull events. It hunts for the header, checks LEN and the checksum,
// skips garbage and resynchronises one byte past a bad header, so a frame that starts
// inside a corrupt one is still found. It never reads outside what it was fed.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>

#include "protocol/packet.h"

namespace sms::protocol {

struct DecodeEvent {
  enum class Kind : std::uint8_t {
    Frame,          // `packet` is valid
    ChecksumError,  // a whole frame arrived but its CHK is wrong; `packet` holds what it said
    LengthError,    // LEN < 2: cannot be a frame; the header is skipped
  };
  Kind kind = Kind::Frame;
  Packet packet;
  // Bytes discarded before this event's header while hunting (garbage, echo, noise).
  std::size_t skipped_before = 0;
};

class StreamDecoder {
 public:
  explicit StreamDecoder(const PacketFormat& format);

  void feed(std::span<const std::uint8_t> bytes);
  // Next complete event, or nullopt when more bytes are needed.
  std::optional<DecodeEvent> next();
  // Drop everything buffered (e.g. the host flushes before each transmit).
  void reset();

  std::size_t buffered() const;
  // Totals since construction, for bus counters.
  std::size_t discarded_bytes() const { return discarded_bytes_; }
  std::size_t checksum_errors() const { return checksum_errors_; }
  std::size_t length_errors() const { return length_errors_; }

 private:
  const PacketFormat& format_;
  Bytes buffer_;
  std::size_t discarded_bytes_ = 0;
  std::size_t checksum_errors_ = 0;
  std::size_t length_errors_ = 0;
};

}  // namespace sms::protocol
