// libFuzzer target: protocol::tcp::MbapDecoder (the gateway's Modbus TCP reader) and the PDU
// helpers of protocol/modbus_tcp.h. Input: fuzz_support.h's chunked layout; the boundary op is
// reset(), which a session does when it starts over on a new connection.
//
// The decoder is compared with a reference reader written here the plain way (walk the whole
// segment since the last reset, header by header), which cannot get chunking wrong:
//   - after every feed the decoder has produced exactly the reference's events, in order;
//   - a Frame re-encodes to the bytes it came from; a BadHeader names the transaction and closes;
//   - after a BadHeader nothing more comes out, whatever is fed; otherwise less than one ADU
//     stays buffered once drained.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <variant>
#include <vector>

#include "fuzz_support.h"
#include "protocol/modbus_tcp.h"

namespace {

namespace tcp = sms::protocol::tcp;
using sms::fuzz::hex;

std::uint16_t big_endian_at(std::span<const std::uint8_t> bytes, std::size_t offset) {
  return static_cast<std::uint16_t>(bytes[offset] << 8 | bytes[offset + 1]);
}

// The reference: what a reader holding the whole segment would report.
struct ReferenceReader {
  std::vector<std::uint8_t> segment;
  std::size_t offset = 0;
  bool failed = false;

  struct Event {
    tcp::MbapEvent event;
    std::size_t offset = 0;  // where its header starts in `segment`
  };
  // Events that became complete since the last call.
  std::vector<Event> advance() {
    std::vector<Event> events;
    while (!failed && segment.size() - offset >= tcp::kMbapHeaderSize) {
      const auto rest = std::span<const std::uint8_t>(segment).subspan(offset);
      const std::uint16_t transaction = big_endian_at(rest, 0);
      const std::uint16_t length = big_endian_at(rest, 4);
      if (big_endian_at(rest, 2) != 0 || length < 2 || length > 254) {
        failed = true;
        events.push_back({tcp::BadHeader{"", transaction, true}, offset});
        break;
      }
      if (rest.size() < 6U + length) break;
      const tcp::Frame frame{transaction, 0, rest[6],
                             sms::protocol::Bytes(rest.begin() + 7, rest.begin() + 6 + length)};
      events.push_back({frame, offset});
      offset += 6U + length;
    }
    return events;
  }
};

void check_pdu_helpers(const tcp::Frame& frame) {
  const auto& pdu = frame.pdu;
  const auto code = tcp::exception_code_of(pdu);
  const bool is_exception = pdu.size() == 2 && (pdu[0] & 0x80) != 0;
  SMS_FUZZ_CHECK(code.has_value() == is_exception && (!code || *code == pdu[1]),
                 "exception_code_of(" + hex(pdu) + ") is wrong");
  const auto answer = tcp::exception_pdu(pdu[0], pdu.back());
  SMS_FUZZ_CHECK(answer.size() == 2 && answer[0] == (pdu[0] | 0x80) && tcp::exception_code_of(answer) == pdu.back(),
                 "exception_pdu does not round-trip for " + hex(pdu));
}

class Checker {
 public:
  void feed(std::span<const std::uint8_t> chunk) {
    const bool failed_before = decoder_.failed();
    const std::size_t buffered_before = decoder_.buffered();
    decoder_.feed(chunk);
    if (!failed_before) reference_.segment.insert(reference_.segment.end(), chunk.begin(), chunk.end());
    if (failed_before) {
      SMS_FUZZ_CHECK(decoder_.buffered() == buffered_before, "a failed decoder took more bytes");
    }

    std::vector<tcp::MbapEvent> events;
    while (auto event = decoder_.next()) events.push_back(std::move(*event));
    const auto expected = reference_.advance();
    SMS_FUZZ_CHECK(events.size() == expected.size(), "decoder gave " + std::to_string(events.size()) +
                                                         " events, the reference " + std::to_string(expected.size()) +
                                                         ", on segment " + hex(reference_.segment));
    for (std::size_t i = 0; i < events.size(); ++i) check_event(events[i], expected[i]);

    SMS_FUZZ_CHECK(decoder_.failed() == reference_.failed, "failed() disagrees with the reference");
    if (!decoder_.failed()) {
      SMS_FUZZ_CHECK(decoder_.buffered() == reference_.segment.size() - reference_.offset,
                     "buffered() is " + std::to_string(decoder_.buffered()) + ", the reference holds " +
                         std::to_string(reference_.segment.size() - reference_.offset));
      SMS_FUZZ_CHECK(decoder_.buffered() < tcp::kMaxAduSize, "a whole ADU stayed buffered");
    }
  }

  void reset() {
    decoder_.reset();
    reference_ = ReferenceReader{};
    SMS_FUZZ_CHECK(decoder_.buffered() == 0 && !decoder_.failed(), "reset() did not start over");
  }

 private:
  void check_event(const tcp::MbapEvent& event, const ReferenceReader::Event& reference) {
    const tcp::MbapEvent& expected = reference.event;
    SMS_FUZZ_CHECK(event.index() == expected.index(),
                   "event kind differs from the reference on segment " + hex(reference_.segment));
    if (const auto* frame = std::get_if<tcp::Frame>(&event)) {
      SMS_FUZZ_CHECK(*frame == std::get<tcp::Frame>(expected),
                     "frame differs from the reference on segment " + hex(reference_.segment));
      SMS_FUZZ_CHECK(!frame->pdu.empty() && frame->pdu.size() <= tcp::kMaxPduSize,
                     "PDU of " + std::to_string(frame->pdu.size()) + " bytes");
      const auto encoded = tcp::encode_mbap(*frame);
      const auto original = std::span<const std::uint8_t>(reference_.segment).subspan(reference.offset, encoded.size());
      SMS_FUZZ_CHECK(std::equal(encoded.begin(), encoded.end(), original.begin(), original.end()),
                     "frame re-encodes to " + hex(encoded) + ", the stream held " + hex(original));
      check_pdu_helpers(*frame);
      return;
    }
    const auto& bad = std::get<tcp::BadHeader>(event);
    SMS_FUZZ_CHECK(bad.transaction_id == std::get<tcp::BadHeader>(expected).transaction_id,
                   "BadHeader names the wrong transaction");
    SMS_FUZZ_CHECK(bad.close_connection && !bad.reason.empty(), "BadHeader without a reason or close");
  }

  tcp::MbapDecoder decoder_;
  ReferenceReader reference_;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const auto input = sms::fuzz::split_chunked_input(std::span<const std::uint8_t>(data, size));
  Checker checker;
  sms::fuzz::play_chunked(
      input, [&](std::span<const std::uint8_t> chunk) { checker.feed(chunk); }, [&] { checker.reset(); });
  return 0;
}
