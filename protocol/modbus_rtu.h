#pragma once
// Modbus-RTU framing for the simulator's SMSMB servos and for tests (SPEC §1.3). The
// gateway's RTU master side uses libmodbus; this is the slave side, sans-IO.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>

#include "protocol/packet.h"

namespace sms::protocol::rtu {

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
class RequestDecoder {
 public:
  struct Event {
    enum class Kind : std::uint8_t { Frame, CrcError };
    Kind kind = Kind::Frame;
    Adu adu;
  };
  void feed(std::span<const std::uint8_t> bytes);
  std::optional<Event> next();
  // The line went silent: whatever is buffered is one frame (checked), or noise.
  std::optional<Event> end_of_frame();
  void reset();
  std::size_t buffered() const { return buffer_.size(); }
  std::size_t crc_errors() const { return crc_errors_; }

 private:
  Bytes buffer_;
  std::size_t crc_errors_ = 0;
};

}  // namespace sms::protocol::rtu
