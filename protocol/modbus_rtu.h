#pragma once
// Modbus-RTU framing for the simulator's SMSMB servos and for tests (docs/PROTOCOL.md §1.3). The
// gateway's RTU master side uses libmodbus; this is the slave side, sans-IO.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>

#include "protocol/packet.h"

namespace sms::protocol::rtu {

// slave(1) + PDU(<= 253) + CRC(2) (Modbus over serial line v1.02 §2.5.1).
inline constexpr std::size_t kMaxAduSize = 256;
inline constexpr std::size_t kMaxPduSize = kMaxAduSize - 3;
// slave + function + CRC: the shortest frame (FC 0x11 and 0x41 requests).
inline constexpr std::size_t kMinAduSize = 4;

// CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF), computed with boost::crc.
std::uint16_t crc16(std::span<const std::uint8_t> bytes);

// slave | pdu | CRC low | CRC high
Bytes frame(std::uint8_t slave, std::span<const std::uint8_t> pdu);

struct Adu {
  std::uint8_t slave = 0;
  Bytes pdu;  // function code first, no CRC
  friend bool operator==(const Adu&, const Adu&) = default;
};

// Request decoder for a slave. A request's length follows from its function code for
// every code the servos know (01 02 03 04 05 06 0F 10 11 17 41); for any other code the
// frame ends at the 3.5-character silence, which the caller signals with end_of_frame().
//
// Use: feed(), then next() until nullopt; when the line has been silent for 3.5 characters,
// end_of_frame() once. After a CRC error the decoder reports it once, then slides one byte at
// a time looking for a frame whose CRC checks, silently, until a frame is found or the line
// goes silent (a real slave ignores the rest of a corrupt frame the same way). Unknown
// function codes wait for end_of_frame(), but never past kMaxAduSize bytes.
class RequestDecoder {
 public:
  struct Event {
    enum class Kind : std::uint8_t { Frame, CrcError };
    Kind kind = Kind::Frame;
    Adu adu;  // for CrcError: the bytes as received, CRC removed
  };
  void feed(std::span<const std::uint8_t> bytes);
  std::optional<Event> next();
  // The line went silent: whatever is buffered is one frame (checked), or noise. Fewer than
  // kMinAduSize bytes, or the tail of a frame already reported as a CRC error, are noise:
  // dropped and counted in discarded_bytes(), no event.
  std::optional<Event> end_of_frame();
  void reset();
  std::size_t buffered() const { return buffer_.size(); }
  std::size_t crc_errors() const { return crc_errors_; }
  std::size_t discarded_bytes() const { return discarded_bytes_; }

 private:
  void discard(std::size_t count);
  Bytes buffer_;
  bool resyncing_ = false;  // a CRC error was reported; slide silently until a frame checks
  std::size_t crc_errors_ = 0;
  std::size_t discarded_bytes_ = 0;
};

}  // namespace sms::protocol::rtu
