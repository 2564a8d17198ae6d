#include "protocol/modbus_tcp.h"

#include <stdexcept>
#include <string>

namespace sms::protocol::tcp {
namespace {

std::uint16_t big_endian_at(std::span<const std::uint8_t> bytes, std::size_t offset) {
  return static_cast<std::uint16_t>((bytes[offset] << 8) | bytes[offset + 1]);
}

void append_big_endian(Bytes& out, std::uint16_t value) {
  out.push_back(static_cast<std::uint8_t>(value >> 8));
  out.push_back(static_cast<std::uint8_t>(value & 0xFF));
}

}  // namespace

void MbapDecoder::feed(std::span<const std::uint8_t> bytes) {
  if (failed_) return;  // the connection is being closed; nothing after a bad header counts
  if (consumed_ > 0) {
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(consumed_));
    consumed_ = 0;
  }
  buffer_.insert(buffer_.end(), bytes.begin(), bytes.end());
}

std::optional<MbapEvent> MbapDecoder::next() {
  if (failed_) return std::nullopt;
  const std::span<const std::uint8_t> pending = std::span<const std::uint8_t>(buffer_).subspan(consumed_);
  if (pending.size() < kMbapHeaderSize) return std::nullopt;

  const std::uint16_t transaction_id = big_endian_at(pending, 0);
  const std::uint16_t protocol_id = big_endian_at(pending, 2);
  const std::uint16_t length = big_endian_at(pending, 4);
  // Judge the header as soon as it is complete: waiting for the body a lying length field
  // announces would hold the connection open for bytes that never come.
  if (protocol_id != 0 || length < kMinLengthField || length > kMaxLengthField) {
    failed_ = true;
    std::string reason = "MBAP header of transaction " + std::to_string(transaction_id) + ": ";
    if (protocol_id != 0) {
      reason += "protocol id " + std::to_string(protocol_id) + " is not Modbus (0)";
    } else {
      reason += "length field " + std::to_string(length) + " outside " + std::to_string(kMinLengthField) + ".." +
                std::to_string(kMaxLengthField) + " (unit id + PDU of 1..253 bytes)";
    }
    reason += "; the stream cannot be resynchronised, close the connection";
    return BadHeader{std::move(reason), transaction_id, true};
  }

  const std::size_t adu_size = kMbapHeaderSize - 1 + length;
  if (pending.size() < adu_size) return std::nullopt;

  Frame frame;
  frame.transaction_id = transaction_id;
  frame.protocol_id = protocol_id;
  frame.unit_id = pending[6];
  frame.pdu.assign(pending.begin() + kMbapHeaderSize, pending.begin() + static_cast<std::ptrdiff_t>(adu_size));
  consumed_ += adu_size;
  if (consumed_ == buffer_.size()) {
    buffer_.clear();
    consumed_ = 0;
  }
  return frame;
}

void MbapDecoder::reset() {
  buffer_.clear();
  consumed_ = 0;
  failed_ = false;
}

Bytes encode_mbap(std::uint16_t transaction_id, std::uint8_t unit_id, std::span<const std::uint8_t> pdu) {
  if (pdu.empty() || pdu.size() > kMaxPduSize) {
    throw std::length_error("encode_mbap: PDU of " + std::to_string(pdu.size()) + " bytes; a Modbus PDU holds 1.." +
                            std::to_string(kMaxPduSize));
  }
  Bytes out;
  out.reserve(kMbapHeaderSize + pdu.size());
  append_big_endian(out, transaction_id);
  append_big_endian(out, 0);  // protocol id: Modbus
  append_big_endian(out, static_cast<std::uint16_t>(1 + pdu.size()));
  out.push_back(unit_id);
  out.insert(out.end(), pdu.begin(), pdu.end());
  return out;
}

Bytes encode_mbap(const Frame& frame) { return encode_mbap(frame.transaction_id, frame.unit_id, frame.pdu); }

Bytes exception_pdu(std::uint8_t function, std::uint8_t code) {
  return Bytes{static_cast<std::uint8_t>(function | 0x80), code};
}

std::optional<std::uint8_t> exception_code_of(std::span<const std::uint8_t> pdu) {
  if (pdu.size() != 2 || (pdu[0] & 0x80) == 0) return std::nullopt;
  return pdu[1];
}

}  // namespace sms::protocol::tcp
