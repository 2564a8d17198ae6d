// libFuzzer target: protocol::StreamDecoder, built once per packet format (SMS_FUZZ_PACKET_FORMAT
// is kFeetechFormat or kD55dFormat). Input: fuzz_support.h's chunked layout; the boundary op is
// reset(), as the host does before each transmit.
//
// Invariants, checked after every feed and every event:
//   - every byte fed is in exactly one place: a Frame, discarded_bytes(), or buffered();
//   - a Frame is the exact bytes of the stream where it started and re-encodes to them
//     (so its checksum is valid); a ChecksumError / LengthError names the bytes it rejected;
//   - once drained, fewer bytes than the largest frame stay buffered;
//   - the error counters equal the error events; after reset() a clean frame decodes alone.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "fuzz_support.h"
#include "protocol/instructions.h"
#include "protocol/packet.h"
#include "protocol/stream_decoder.h"

namespace {

using sms::fuzz::hex;
using sms::protocol::DecodeEvent;
using sms::protocol::Packet;
using sms::protocol::StreamDecoder;

constexpr const sms::protocol::PacketFormat& kFormat = sms::protocol::SMS_FUZZ_PACKET_FORMAT;
constexpr std::uint8_t kImpossibleId = 0xFF;  // no servo has it; the decoder hunts past `header FF`

class Checker {
 public:
  explicit Checker(std::span<const std::uint8_t> stream) : stream_(stream), decoder_(kFormat) {}

  void feed(std::span<const std::uint8_t> chunk) {
    decoder_.feed(chunk);
    fed_ += chunk.size();
    check_accounting("after a feed");
    drain();
  }

  void reset() {
    decoder_.reset();
    SMS_FUZZ_CHECK(decoder_.buffered() == 0, "reset() left bytes buffered");
    check_accounting("after reset()");
  }

  // After everything: a clean frame on a reset decoder must come out alone and unchanged.
  void check_clean_frame_after_reset() {
    reset();
    const Packet ping = sms::protocol::ping(1);
    const auto frame = sms::protocol::encode(kFormat, ping);
    decoder_.feed(frame);
    const auto event = decoder_.next();
    SMS_FUZZ_CHECK(event && event->kind == DecodeEvent::Kind::Frame && event->packet == ping,
                   "a PING frame fed after reset() did not decode: " + hex(frame));
    SMS_FUZZ_CHECK(!decoder_.next() && decoder_.buffered() == 0, "PING after reset() left an event or bytes");
  }

 private:
  void drain() {
    while (const auto event = decoder_.next()) {
      check_event(*event);
      check_accounting("after an event");
    }
    SMS_FUZZ_CHECK(decoder_.buffered() < StreamDecoder::kMaxFrameSize,
                   std::to_string(decoder_.buffered()) + " bytes still buffered once drained; a frame is at most " +
                       std::to_string(StreamDecoder::kMaxFrameSize));
    SMS_FUZZ_CHECK(decoder_.checksum_errors() == checksum_events_, "checksum_errors() differs from the events");
    SMS_FUZZ_CHECK(decoder_.length_errors() == length_events_, "length_errors() differs from the events");
  }

  void check_event(const DecodeEvent& event) {
    const std::size_t size = sms::protocol::kMinFrameSize + event.packet.params.size();
    switch (event.kind) {
      case DecodeEvent::Kind::Frame: {
        // Nothing is discarded after a frame is taken, so it starts right after what went before.
        const std::size_t start = frame_bytes_ + decoder_.discarded_bytes();
        SMS_FUZZ_CHECK(size <= StreamDecoder::kMaxFrameSize, "frame larger than kMaxFrameSize");
        SMS_FUZZ_CHECK(start + size <= fed_, "frame extends past the bytes fed");
        const auto encoded = sms::protocol::encode(kFormat, event.packet);
        const auto original = stream_.subspan(start, size);
        SMS_FUZZ_CHECK(std::equal(encoded.begin(), encoded.end(), original.begin(), original.end()),
                       "decoded frame re-encodes to " + hex(encoded) + " but the stream held " + hex(original));
        SMS_FUZZ_CHECK(event.packet.id != kImpossibleId, "frame with ID 0xFF: " + hex(original));
        frame_bytes_ += size;
        break;
      }
      case DecodeEvent::Kind::ChecksumError: {
        // The decoder discards the first header byte of the rejected frame before returning.
        const std::size_t start = frame_bytes_ + decoder_.discarded_bytes() - 1;
        SMS_FUZZ_CHECK(start + size <= fed_, "checksum error on a frame not fully fed");
        const auto original = stream_.subspan(start, size);
        const Packet said{original[2], original[4], sms::protocol::Bytes(original.begin() + 5, original.end() - 1)};
        SMS_FUZZ_CHECK(original[0] == kFormat.header[0] && original[1] == kFormat.header[1],
                       "checksum error without a header: " + hex(original));
        SMS_FUZZ_CHECK(original[3] == event.packet.params.size() + 2 && said == event.packet,
                       "checksum error reports a packet other than the bytes " + hex(original));
        SMS_FUZZ_CHECK(sms::protocol::checksum(kFormat, original.subspan(2, size - 3)) != original.back(),
                       "checksum error on a frame whose checksum is right: " + hex(original));
        ++checksum_events_;
        break;
      }
      case DecodeEvent::Kind::LengthError: {
        const std::size_t start = frame_bytes_ + decoder_.discarded_bytes() - 1;
        SMS_FUZZ_CHECK(start + 4 <= fed_, "length error before LEN arrived");
        const auto original = stream_.subspan(start, 4);
        SMS_FUZZ_CHECK(original[0] == kFormat.header[0] && original[1] == kFormat.header[1] &&
                           original[2] == event.packet.id && original[3] < 2,
                       "length error on bytes " + hex(original));
        ++length_events_;
        break;
      }
    }
  }

  void check_accounting(const char* when) {
    const std::size_t accounted = frame_bytes_ + decoder_.discarded_bytes() + decoder_.buffered();
    SMS_FUZZ_CHECK(accounted == fed_, std::string(when) + ": fed " + std::to_string(fed_) + " bytes, frames " +
                                          std::to_string(frame_bytes_) + " + discarded " +
                                          std::to_string(decoder_.discarded_bytes()) + " + buffered " +
                                          std::to_string(decoder_.buffered()));
  }

  std::span<const std::uint8_t> stream_;
  StreamDecoder decoder_;
  std::size_t fed_ = 0;
  std::size_t frame_bytes_ = 0;
  std::size_t checksum_events_ = 0;
  std::size_t length_events_ = 0;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const auto input = sms::fuzz::split_chunked_input(std::span<const std::uint8_t>(data, size));
  Checker checker(input.stream);
  sms::fuzz::play_chunked(
      input, [&](std::span<const std::uint8_t> chunk) { checker.feed(chunk); }, [&] { checker.reset(); });
  checker.check_clean_frame_after_reset();
  return 0;
}
