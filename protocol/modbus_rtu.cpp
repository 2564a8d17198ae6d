#include "protocol/modbus_rtu.h"

#include <algorithm>
#include <array>
#include <variant>

#include <boost/crc.hpp>

namespace sms::protocol::rtu {
namespace {

// How long a request is, by function code (Modbus application protocol v1.1b3 §6, and the
// Feetech codes of docs/PROTOCOL.md §1.3). size = fixed_size + the byte-count field at byte_count_offset.
constexpr std::size_t kNoByteCount = 0;  // offset 0 is the slave address, never a count
struct RequestLayout {
  std::uint8_t function = 0;
  std::size_t fixed_size = 0;  // whole ADU: slave, function, fields, CRC
  std::size_t byte_count_offset = kNoByteCount;
};
constexpr std::array<RequestLayout, 11> kRequestLayouts{{
    {0x01, 8},       // read coils: addr, quantity
    {0x02, 8},       // read discrete inputs
    {0x03, 8},       // read holding registers
    {0x04, 8},       // read input registers
    {0x05, 8},       // write single coil: addr, value
    {0x06, 8},       // write single register
    {0x0F, 9, 6},    // write multiple coils: addr, quantity, byte count, data
    {0x10, 9, 6},    // write multiple registers
    {0x11, 4},       // report slave id: no fields (docs/PROTOCOL.md §1.3)
    {0x17, 13, 10},  // read/write multiple: read addr, qty, write addr, qty, byte count, data
    // Feetech restart: docs/PROTOCOL.md §1.3 says only "0x41 restart (0 = every slave)"; neither the seed
    // documents nor Feetech's wiki as searchable here give its layout. Decision: no fields,
    // like 0x11 (slave, 0x41, CRC), "0 = every slave" being the broadcast address.
    {0x41, 4},
}};

static_assert(std::is_sorted(kRequestLayouts.begin(), kRequestLayouts.end(),
                             [](const RequestLayout& a, const RequestLayout& b) { return a.function < b.function; }),
              "kRequestLayouts must stay in function-code order");

const RequestLayout* layout_of(std::uint8_t function) {
  const auto* it = std::find_if(kRequestLayouts.begin(), kRequestLayouts.end(),
                                [function](const RequestLayout& layout) { return layout.function == function; });
  return it == kRequestLayouts.end() ? nullptr : it;
}

struct SizeUnknown {};  // function code without a layout: the frame ends at silence
// The request's whole size, 0 while too few bytes have arrived to tell, or SizeUnknown.
std::variant<std::size_t, SizeUnknown> request_size(std::span<const std::uint8_t> bytes) {
  if (bytes.size() < 2) return std::size_t{0};
  const RequestLayout* layout = layout_of(bytes[1]);
  if (layout == nullptr) return SizeUnknown{};
  if (layout->byte_count_offset == kNoByteCount) return layout->fixed_size;
  if (bytes.size() <= layout->byte_count_offset) return std::size_t{0};
  return layout->fixed_size + bytes[layout->byte_count_offset];
}

bool crc_matches(std::span<const std::uint8_t> adu) {
  if (adu.size() < kMinAduSize) return false;
  const std::uint16_t crc = crc16(adu.first(adu.size() - 2));
  return adu[adu.size() - 2] == (crc & 0xFF) && adu[adu.size() - 1] == (crc >> 8);
}

Adu adu_of(std::span<const std::uint8_t> adu) { return Adu{adu[0], Bytes(adu.begin() + 1, adu.end() - 2)}; }

}  // namespace

std::uint16_t crc16(std::span<const std::uint8_t> bytes) {
  // CRC-16/MODBUS: poly 0x8005 reflected (0xA001), init 0xFFFF, no final xor.
  boost::crc_optimal<16, 0x8005, 0xFFFF, 0, true, true> crc;
  crc.process_bytes(bytes.data(), bytes.size());
  return crc.checksum();
}

Bytes frame(std::uint8_t slave, std::span<const std::uint8_t> pdu) {
  Bytes adu;
  adu.reserve(pdu.size() + 3);
  adu.push_back(slave);
  adu.insert(adu.end(), pdu.begin(), pdu.end());
  const std::uint16_t crc = crc16(adu);
  adu.push_back(static_cast<std::uint8_t>(crc & 0xFF));  // CRC low byte first on the wire
  adu.push_back(static_cast<std::uint8_t>(crc >> 8));
  return adu;
}

void RequestDecoder::feed(std::span<const std::uint8_t> bytes) {
  buffer_.insert(buffer_.end(), bytes.begin(), bytes.end());
}

void RequestDecoder::discard(std::size_t count) {
  buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(count));
  discarded_bytes_ += count;
}

std::optional<RequestDecoder::Event> RequestDecoder::next() {
  while (!buffer_.empty()) {
    const auto size = request_size(buffer_);
    if (std::holds_alternative<SizeUnknown>(size)) {
      // Wait for the silence, unless this cannot be the start of a frame any more.
      if (!resyncing_ && buffer_.size() <= kMaxAduSize) return std::nullopt;
      discard(1);
      continue;
    }
    const std::size_t frame_size = std::get<std::size_t>(size);
    if (frame_size > kMaxAduSize) {
      // A byte count no valid request carries (e.g. FC 0x10 announcing 250 bytes): not a
      // frame start. Slide on as after a CRC error rather than wait for bytes never sent.
      resyncing_ = true;
      discard(1);
      continue;
    }
    if (frame_size == 0 || buffer_.size() < frame_size) return std::nullopt;

    const auto candidate = std::span<const std::uint8_t>(buffer_).first(frame_size);
    if (crc_matches(candidate)) {
      Event event{Event::Kind::Frame, adu_of(candidate)};
      buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(frame_size));
      resyncing_ = false;
      return event;
    }
    if (resyncing_) {
      discard(1);
      continue;
    }
    // Report once, then look for a frame starting inside this one.
    ++crc_errors_;
    resyncing_ = true;
    Event event{Event::Kind::CrcError, adu_of(candidate)};
    discard(1);
    return event;
  }
  return std::nullopt;
}

std::optional<RequestDecoder::Event> RequestDecoder::end_of_frame() {
  std::optional<Event> event;
  if (crc_matches(buffer_)) {
    event = Event{Event::Kind::Frame, adu_of(buffer_)};
    buffer_.clear();
  } else if (!resyncing_ && buffer_.size() >= kMinAduSize) {
    ++crc_errors_;
    event = Event{Event::Kind::CrcError, adu_of(buffer_)};
    discard(buffer_.size());
  } else {
    discard(buffer_.size());
  }
  resyncing_ = false;
  return event;
}

void RequestDecoder::reset() {
  discard(buffer_.size());
  resyncing_ = false;
}

}  // namespace sms::protocol::rtu
