#pragma once
// Modbus TCP, sans-IO: the MBAP reader the gateway's sessions feed with whatever the socket
// delivered, and the small PDU helpers its answers need. No Asio here.
//   MBAP: transaction id (2) | protocol id (2, always 0) | length (2) | unit id (1) | PDU
// All MBAP fields are big-endian; `length` counts the unit id plus the PDU.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <variant>

#include "protocol/packet.h"

namespace sms::protocol::tcp {

inline constexpr std::size_t kMbapHeaderSize = 7;  // up to and including the unit id
inline constexpr std::size_t kMaxPduSize = 253;    // Modbus application protocol v1.1b3 §4.1
inline constexpr std::size_t kMinLengthField = 2;  // unit id + function code
inline constexpr std::size_t kMaxLengthField = 1 + kMaxPduSize;
inline constexpr std::size_t kMaxAduSize = kMbapHeaderSize - 1 + kMaxLengthField;  // 260

// Standard exception codes (Modbus application protocol §7), as docs/PLC_GUIDE.md uses them.
namespace exception_code {
inline constexpr std::uint8_t kIllegalFunction = 0x01;
inline constexpr std::uint8_t kIllegalDataAddress = 0x02;
inline constexpr std::uint8_t kIllegalDataValue = 0x03;
inline constexpr std::uint8_t kServerDeviceFailure = 0x04;
inline constexpr std::uint8_t kAcknowledge = 0x05;
inline constexpr std::uint8_t kServerDeviceBusy = 0x06;
inline constexpr std::uint8_t kGatewayPathUnavailable = 0x0A;
inline constexpr std::uint8_t kGatewayTargetFailedToRespond = 0x0B;
}  // namespace exception_code

// One complete request (or response) ADU.
struct Frame {
  std::uint16_t transaction_id = 0;
  std::uint16_t protocol_id = 0;  // always 0 in a Frame: anything else is a BadHeader
  std::uint8_t unit_id = 0;
  Bytes pdu;  // function code first; 1..253 bytes
  friend bool operator==(const Frame&, const Frame&) = default;
};

// The header cannot belong to a Modbus TCP stream (protocol id != 0, length field < 2 or
// > 254). The byte stream has no way to resynchronise after this, so the server must close
// the connection (Modbus messaging on TCP/IP implementation guide §4.4.1.2 / §3.1.3): after a
// BadHeader the decoder stays failed and yields nothing more until reset().
struct BadHeader {
  std::string reason;  // what was wrong, with the offending values, for the log
  std::uint16_t transaction_id = 0;
  bool close_connection = true;  // always true: said explicitly so callers need not guess
  friend bool operator==(const BadHeader&, const BadHeader&) = default;
};

using MbapEvent = std::variant<Frame, BadHeader>;

class MbapDecoder {
 public:
  // Appends bytes in any chunking. The buffer never holds more than one ADU plus what was
  // fed since the last next(): call next() until it returns nullopt after every feed().
  void feed(std::span<const std::uint8_t> bytes);
  // Next complete event, or nullopt when more bytes are needed (or after a BadHeader).
  std::optional<MbapEvent> next();
  // True after a BadHeader: the connection is to be closed.
  bool failed() const { return failed_; }
  void reset();
  std::size_t buffered() const { return buffer_.size() - consumed_; }

 private:
  Bytes buffer_;
  std::size_t consumed_ = 0;  // bytes at the front of buffer_ already turned into events
  bool failed_ = false;
};

// MBAP header (protocol id 0, length = 1 + pdu size) followed by the PDU.
// Throws std::length_error when the PDU is empty or longer than kMaxPduSize.
Bytes encode_mbap(std::uint16_t transaction_id, std::uint8_t unit_id, std::span<const std::uint8_t> pdu);
Bytes encode_mbap(const Frame& frame);

// Exception response PDU: function | 0x80, code.
Bytes exception_pdu(std::uint8_t function, std::uint8_t code);
// The exception code when `pdu` is an exception response (function bit 7 set, 2 bytes).
std::optional<std::uint8_t> exception_code_of(std::span<const std::uint8_t> pdu);

}  // namespace sms::protocol::tcp
