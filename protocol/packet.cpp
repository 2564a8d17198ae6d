#include "protocol/packet.h"

#include <numeric>
#include <stdexcept>
#include <string>

namespace sms::protocol {

std::uint8_t checksum(const PacketFormat& format, std::span<const std::uint8_t> body) {
  const unsigned sum = std::accumulate(body.begin(), body.end(), 0U);
  // docs/PROTOCOL.md §1.1: feetech inverts the sum; §1.2: d55d sends it plain.
  return static_cast<std::uint8_t>((format.inverted_checksum ? ~sum : sum) & 0xFFU);
}

Bytes encode(const PacketFormat& format, const Packet& packet) {
  if (packet.params.size() > kMaxParams) {
    throw std::length_error(std::string(format.name) + " packet for id " + std::to_string(packet.id) + ", code " +
                            std::to_string(packet.code) + ": " + std::to_string(packet.params.size()) +
                            " parameter bytes, LEN allows at most " + std::to_string(kMaxParams));
  }
  Bytes frame;
  frame.reserve(kMinFrameSize + packet.params.size());
  frame.insert(frame.end(), format.header.begin(), format.header.end());
  frame.push_back(packet.id);
  frame.push_back(static_cast<std::uint8_t>(packet.params.size() + 2));
  frame.push_back(packet.code);
  frame.insert(frame.end(), packet.params.begin(), packet.params.end());
  const auto body = std::span<const std::uint8_t>(frame).subspan(format.header.size());
  frame.push_back(checksum(format, body));
  return frame;
}

}  // namespace sms::protocol
