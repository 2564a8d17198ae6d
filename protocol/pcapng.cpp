#include "protocol/pcapng.h"

#include <stdexcept>

namespace sms::protocol::pcapng {
namespace {

constexpr std::uint32_t kSectionHeader = 0x0A0D0D0A;
constexpr std::uint32_t kInterfaceDescription = 0x00000001;
constexpr std::uint32_t kEnhancedPacket = 0x00000006;
constexpr std::uint32_t kByteOrderMagic = 0x1A2B3C4D;

constexpr std::uint16_t kOptEndOfOptions = 0;
constexpr std::uint16_t kOptComment = 1;
constexpr std::uint16_t kShbUserApplication = 4;
constexpr std::uint16_t kIfName = 2;
constexpr std::uint16_t kIfDescription = 3;
constexpr std::uint16_t kIfTsResolution = 9;
constexpr std::uint16_t kEpbFlags = 2;
// epb_flags bits 0-1: 01 inbound, 10 outbound.
constexpr std::uint32_t kFlagInbound = 1;
constexpr std::uint32_t kFlagOutbound = 2;

void put16(Bytes& out, std::uint16_t value) {
  out.push_back(static_cast<std::uint8_t>(value));
  out.push_back(static_cast<std::uint8_t>(value >> 8));
}
void put32(Bytes& out, std::uint32_t value) {
  put16(out, static_cast<std::uint16_t>(value));
  put16(out, static_cast<std::uint16_t>(value >> 16));
}
void pad32(Bytes& out) {
  while (out.size() % 4 != 0) out.push_back(0);
}
void put_option(Bytes& out, std::uint16_t code, std::span<const std::uint8_t> value) {
  if (value.size() > 0xFFFF) throw std::length_error("pcapng option longer than 65535 bytes");
  put16(out, code);
  put16(out, static_cast<std::uint16_t>(value.size()));
  out.insert(out.end(), value.begin(), value.end());
  pad32(out);
}
void put_option(Bytes& out, std::uint16_t code, std::string_view text) {
  put_option(out, code, std::span(reinterpret_cast<const std::uint8_t*>(text.data()), text.size()));
}
void end_options(Bytes& out) {
  put16(out, kOptEndOfOptions);
  put16(out, 0);
}

// Every block: type, total length, body, total length again. `body` fills in between.
template <typename Body>
void block(Bytes& out, std::uint32_t type, Body&& body) {
  const std::size_t start = out.size();
  put32(out, type);
  put32(out, 0);  // patched below
  body(out);
  pad32(out);
  const auto total = static_cast<std::uint32_t>(out.size() - start + 4);
  put32(out, total);
  for (int i = 0; i < 4; ++i) out[start + 4 + i] = static_cast<std::uint8_t>(total >> (8 * i));
}

}  // namespace

Writer::Writer(std::string_view application) {
  block(out_, kSectionHeader, [&](Bytes& out) {
    put32(out, kByteOrderMagic);
    put16(out, 1);           // major version
    put16(out, 0);           // minor version
    put32(out, 0xFFFFFFFF);  // section length: not given
    put32(out, 0xFFFFFFFF);
    put_option(out, kShbUserApplication, application);
    end_options(out);
  });
}

std::uint32_t Writer::add_interface(std::uint16_t link_type, std::string_view name, std::string_view description) {
  block(out_, kInterfaceDescription, [&](Bytes& out) {
    put16(out, link_type);
    put16(out, 0);  // reserved
    put32(out, 0);  // snap length: none
    put_option(out, kIfName, name);
    if (!description.empty()) put_option(out, kIfDescription, description);
    const std::uint8_t microseconds = 6;  // 10^-6 s
    put_option(out, kIfTsResolution, std::span(&microseconds, 1));
    end_options(out);
  });
  return interfaces_++;
}

void Writer::add_packet(std::uint32_t interface, std::uint64_t time_us, Direction direction,
                        std::span<const std::uint8_t> bytes, std::string_view comment) {
  if (interface >= interfaces_) throw std::out_of_range("pcapng packet on an interface not described");
  block(out_, kEnhancedPacket, [&](Bytes& out) {
    put32(out, interface);
    put32(out, static_cast<std::uint32_t>(time_us >> 32));
    put32(out, static_cast<std::uint32_t>(time_us));
    put32(out, static_cast<std::uint32_t>(bytes.size()));  // captured
    put32(out, static_cast<std::uint32_t>(bytes.size()));  // on the wire
    out.insert(out.end(), bytes.begin(), bytes.end());
    pad32(out);
    Bytes flags;
    put32(flags, direction == Direction::Inbound ? kFlagInbound : kFlagOutbound);
    put_option(out, kEpbFlags, flags);
    if (!comment.empty()) put_option(out, kOptComment, comment);
    end_options(out);
  });
}

}  // namespace sms::protocol::pcapng
