#include "protocol/stream_decoder.h"

#include <utility>

namespace sms::protocol {
namespace {

// Neither protocol gives a servo ID 0xFF (0..253, 254 broadcast). A header followed by 0xFF
// is therefore a stray header byte before the real header (e.g. `FF FF FF 01 ...` on a
// feetech bus after an echo): dropping one byte finds the frame without reporting an error.
constexpr std::uint8_t kImpossibleId = 0xFF;
constexpr std::size_t kIdOffset = 2;
constexpr std::size_t kLenOffset = 3;
constexpr std::size_t kCodeOffset = 4;
constexpr std::size_t kParamsOffset = 5;

}  // namespace

StreamDecoder::StreamDecoder(const PacketFormat& format) : format_(format) {}

std::span<const std::uint8_t> StreamDecoder::pending() const {
  return std::span<const std::uint8_t>(buffer_).subspan(start_);
}

void StreamDecoder::feed(std::span<const std::uint8_t> bytes) {
  if (start_ > 0) {
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(start_));
    start_ = 0;
  }
  buffer_.insert(buffer_.end(), bytes.begin(), bytes.end());
  drop_garbage();
}

void StreamDecoder::discard(std::size_t count) {
  start_ += count;
  skipped_since_event_ += count;
  discarded_bytes_ += count;
}

void StreamDecoder::consume(std::size_t count) { start_ += count; }

void StreamDecoder::drop_garbage() {
  const auto [first, second] = format_.header;
  for (;;) {
    const auto bytes = pending();
    std::size_t candidate = 0;
    // A lone first header byte at the very end may be completed by the next feed.
    while (candidate < bytes.size() &&
           !(bytes[candidate] == first && (candidate + 1 == bytes.size() || bytes[candidate + 1] == second))) {
      ++candidate;
    }
    discard(candidate);
    const auto rest = pending();
    if (rest.size() > kIdOffset && rest[kIdOffset] == kImpossibleId) {
      discard(1);
      continue;
    }
    return;
  }
}

DecodeEvent StreamDecoder::make_event(DecodeEvent::Kind kind, Packet packet) {
  DecodeEvent event{kind, std::move(packet), skipped_since_event_};
  skipped_since_event_ = 0;
  return event;
}

std::optional<DecodeEvent> StreamDecoder::next() {
  drop_garbage();
  const auto bytes = pending();
  if (bytes.size() <= kLenOffset) return std::nullopt;

  const std::uint8_t len = bytes[kLenOffset];
  if (len < 2) {
    // LEN counts CODE and CHK, so < 2 cannot be a frame. Resync one byte past this header.
    ++length_errors_;
    auto event = make_event(DecodeEvent::Kind::LengthError, Packet{bytes[kIdOffset], 0, {}});
    discard(1);
    return event;
  }

  const std::size_t frame_size = kLenOffset + 1 + len;
  if (bytes.size() < frame_size) return std::nullopt;

  const auto frame = bytes.first(frame_size);
  Packet packet{frame[kIdOffset], frame[kCodeOffset], Bytes(frame.begin() + kParamsOffset, frame.end() - 1)};
  const auto body = frame.subspan(kIdOffset, frame_size - kIdOffset - 1);
  if (checksum(format_, body) == frame.back()) {
    auto event = make_event(DecodeEvent::Kind::Frame, std::move(packet));
    consume(frame_size);
    return event;
  }
  // A real frame may start inside this one (a truncated frame followed by a whole one):
  // drop only the first header byte and hunt again.
  ++checksum_errors_;
  auto event = make_event(DecodeEvent::Kind::ChecksumError, std::move(packet));
  event.received_checksum = frame.back();
  discard(1);
  return event;
}

void StreamDecoder::reset() {
  discarded_bytes_ += buffered();
  buffer_.clear();
  start_ = 0;
  skipped_since_event_ = 0;
}

std::size_t StreamDecoder::buffered() const { return buffer_.size() - start_; }

}  // namespace sms::protocol
