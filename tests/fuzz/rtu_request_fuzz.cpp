// libFuzzer target: protocol::rtu::RequestDecoder (the slave side of Modbus RTU, docs/PROTOCOL.md §1.3).
// Input: fuzz_support.h's chunked layout; the boundary op is the 3.5-character silence
// (end_of_frame()), and the line goes silent once more after the last byte.
//
// Invariants:
//   - every byte fed is in exactly one place: a Frame, discarded_bytes(), or buffered();
//   - a Frame is the exact bytes of the stream where it started, re-framed with its CRC;
//     a CrcError names the bytes it rejected, and their CRC is indeed wrong;
//   - next() only completes frames of the function codes whose length it knows;
//   - once drained, at most one ADU (256 bytes) stays buffered; silence empties the buffer;
//   - crc_errors() equals the CrcError events; afterwards the docs/PROTOCOL.md's worked frame decodes.
#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "fuzz_support.h"
#include "protocol/modbus_rtu.h"

namespace {

namespace rtu = sms::protocol::rtu;
using sms::fuzz::hex;

// The codes modbus_rtu.h says a request's length follows from.
constexpr std::array<std::uint8_t, 11> kSizedFunctions{0x01, 0x02, 0x03, 0x04, 0x05, 0x06,
                                                       0x0F, 0x10, 0x11, 0x17, 0x41};

class Checker {
 public:
  explicit Checker(std::span<const std::uint8_t> stream) : stream_(stream) {}

  void feed(std::span<const std::uint8_t> chunk) {
    decoder_.feed(chunk);
    fed_ += chunk.size();
    check_accounting("after a feed");
    while (const auto event = decoder_.next()) {
      check_event(*event, Source::Next, decoder_.discarded_bytes());
      check_accounting("after an event");
    }
    SMS_FUZZ_CHECK(decoder_.buffered() <= rtu::kMaxAduSize,
                   std::to_string(decoder_.buffered()) + " bytes buffered once drained, more than one ADU");
  }

  void silence() {
    const std::size_t discarded_before = decoder_.discarded_bytes();
    if (const auto event = decoder_.end_of_frame()) check_event(*event, Source::Silence, discarded_before);
    SMS_FUZZ_CHECK(decoder_.buffered() == 0, "end_of_frame() left bytes buffered");
    check_accounting("after end_of_frame()");
  }

  void check_worked_frame_decodes() {
    SMS_FUZZ_CHECK(decoder_.crc_errors() == crc_events_, "crc_errors() differs from the CrcError events");
    // docs/PROTOCOL.md §1.3: read the 8 feedback registers of slave 1.
    constexpr std::array<std::uint8_t, 8> kReadFeedback{0x01, 0x03, 0x01, 0x00, 0x00, 0x08, 0x45, 0xF0};
    decoder_.feed(kReadFeedback);
    const auto event = decoder_.next();
    SMS_FUZZ_CHECK(event && event->kind == rtu::RequestDecoder::Event::Kind::Frame && event->adu.slave == 1 &&
                       event->adu.pdu == sms::protocol::Bytes({0x03, 0x01, 0x00, 0x00, 0x08}),
                   "the docs/PROTOCOL.md §1.3 worked frame did not decode after silence");
    SMS_FUZZ_CHECK(decoder_.buffered() == 0 && !decoder_.next(), "worked frame left bytes or events behind");
  }

 private:
  enum class Source { Next, Silence };

  void check_event(const rtu::RequestDecoder::Event& event, Source source, std::size_t discarded_before) {
    const std::size_t size = event.adu.pdu.size() + 3;
    SMS_FUZZ_CHECK(size >= rtu::kMinAduSize && size <= rtu::kMaxAduSize, "event of " + std::to_string(size) + " bytes");
    if (event.kind == rtu::RequestDecoder::Event::Kind::Frame) {
      const std::size_t start = frame_bytes_ + decoder_.discarded_bytes();
      SMS_FUZZ_CHECK(size <= rtu::kMaxAduSize, "frame larger than an ADU");
      SMS_FUZZ_CHECK(start + size <= fed_, "frame extends past the bytes fed");
      const auto original = stream_.subspan(start, size);
      const auto framed = rtu::frame(event.adu.slave, event.adu.pdu);
      SMS_FUZZ_CHECK(std::equal(framed.begin(), framed.end(), original.begin(), original.end()),
                     "decoded ADU re-frames to " + hex(framed) + " but the stream held " + hex(original));
      if (source == Source::Next) {
        SMS_FUZZ_CHECK(
            std::find(kSizedFunctions.begin(), kSizedFunctions.end(), event.adu.pdu[0]) != kSizedFunctions.end(),
            "next() completed a frame of unsized function " + hex(original.subspan(1, 1)));
      }
      frame_bytes_ += size;
      return;
    }
    // CrcError: next() discards one byte of it before returning, silence discards all of it.
    const std::size_t start =
        source == Source::Next ? decoder_.discarded_bytes() - 1 + frame_bytes_ : discarded_before + frame_bytes_;
    SMS_FUZZ_CHECK(start + size <= fed_, "CRC error on bytes not fed");
    const auto original = stream_.subspan(start, size);
    SMS_FUZZ_CHECK(
        original[0] == event.adu.slave && std::equal(event.adu.pdu.begin(), event.adu.pdu.end(), original.begin() + 1),
        "CRC error reports other bytes than the stream's " + hex(original));
    const auto reframed = rtu::frame(event.adu.slave, event.adu.pdu);
    SMS_FUZZ_CHECK(!std::equal(reframed.begin(), reframed.end(), original.begin(), original.end()),
                   "CRC error on a frame whose CRC is right: " + hex(original));
    ++crc_events_;
  }

  void check_accounting(const char* when) {
    const std::size_t accounted = frame_bytes_ + decoder_.discarded_bytes() + decoder_.buffered();
    SMS_FUZZ_CHECK(accounted == fed_, std::string(when) + ": fed " + std::to_string(fed_) + " bytes, frames " +
                                          std::to_string(frame_bytes_) + " + discarded " +
                                          std::to_string(decoder_.discarded_bytes()) + " + buffered " +
                                          std::to_string(decoder_.buffered()));
  }

  std::span<const std::uint8_t> stream_;
  rtu::RequestDecoder decoder_;
  std::size_t fed_ = 0;
  std::size_t frame_bytes_ = 0;
  std::size_t crc_events_ = 0;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const auto input = sms::fuzz::split_chunked_input(std::span<const std::uint8_t>(data, size));
  Checker checker(input.stream);
  sms::fuzz::play_chunked(
      input, [&](std::span<const std::uint8_t> chunk) { checker.feed(chunk); }, [&] { checker.silence(); });
  checker.silence();
  checker.check_worked_frame_decodes();
  return 0;
}
