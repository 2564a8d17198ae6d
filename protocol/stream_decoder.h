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
    LengthError,    // LEN < 2: cannot be a frame; the header is skipped; `packet.id` is the ID it named
  };
  Kind kind = Kind::Frame;
  Packet packet;
  // Bytes discarded before this event's header while hunting (garbage, echo, noise).
  std::size_t skipped_before = 0;
  // ChecksumError: the CHK byte as it came (the frame's bytes as received, for the bus monitor).
  std::uint8_t received_checksum = 0;
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
  // Totals since construction, for bus counters. Every byte fed ends up in exactly one of:
  // a Frame event, discarded_bytes(), or buffered(). Bytes dropped by reset() count as
  // discarded; so does the first byte of a frame that failed its checks (its other bytes
  // are hunted through again and counted when they are dropped).
  std::size_t discarded_bytes() const { return discarded_bytes_; }
  std::size_t checksum_errors() const { return checksum_errors_; }
  std::size_t length_errors() const { return length_errors_; }

  // Largest frame LEN can describe: header, id, LEN = 255, then 255 bytes counted by LEN.
  static constexpr std::size_t kMaxFrameSize = 4 + 255;

 private:
  std::span<const std::uint8_t> pending() const;
  // Drops bytes that cannot start a frame, so garbage alone never accumulates.
  void drop_garbage();
  void discard(std::size_t count);
  void consume(std::size_t count);
  DecodeEvent make_event(DecodeEvent::Kind kind, Packet packet);

  const PacketFormat& format_;
  Bytes buffer_;
  std::size_t start_ = 0;  // buffer_[0, start_) is already consumed or discarded
  std::size_t skipped_since_event_ = 0;
  std::size_t discarded_bytes_ = 0;
  std::size_t checksum_errors_ = 0;
  std::size_t length_errors_ = 0;
};

}  // namespace sms::protocol
