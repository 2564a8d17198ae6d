#pragma once
// A pcapng writer (IETF draft-ietf-opsawg-pcapng), sans-IO: the bytes of a capture file that
// Wireshark and tshark open. Only what the bus monitor needs (docs/MONITOR.md): one section
// (SHB), one interface per bus (IDB, microsecond timestamps), and one Enhanced Packet Block per
// frame with its direction (epb_flags inbound/outbound) and an optional comment. Little-endian.
#include <cstdint>
#include <span>
#include <string_view>

#include "protocol/packet.h"

namespace sms::protocol::pcapng {

// Link types (tcpdump.org LINKTYPE_USER0..15 = 147..162 are for private use). The gateway uses:
// USER0 for feetech `FF FF` and d55d `D5 5D` packet buses (deploy/wireshark/sms_servo.lua), USER1
// for Modbus-RTU buses (slave, PDU, CRC: Wireshark's own `mbrtu` dissector, docs/MONITOR.md).
inline constexpr std::uint16_t kLinkTypeUser0 = 147;
inline constexpr std::uint16_t kLinkTypePacketBus = kLinkTypeUser0;
inline constexpr std::uint16_t kLinkTypeModbusRtu = kLinkTypeUser0 + 1;

enum class Direction : std::uint8_t { Inbound, Outbound };

class Writer {
 public:
  // Starts the section: the Section Header Block, naming the writing program in shb_userappl.
  explicit Writer(std::string_view application);

  // An Interface Description Block (if_name, if_description, if_tsresol = microseconds; no snap
  // length); returns the interface's number for add_packet.
  std::uint32_t add_interface(std::uint16_t link_type, std::string_view name, std::string_view description);

  // An Enhanced Packet Block: `time_us` microseconds since 1970-01-01 UTC; epb_flags carries
  // the direction; `comment` (opt_comment) when not empty.
  void add_packet(std::uint32_t interface, std::uint64_t time_us, Direction direction,
                  std::span<const std::uint8_t> bytes, std::string_view comment = {});

  const Bytes& bytes() const { return out_; }
  Bytes take() { return std::move(out_); }

 private:
  Bytes out_;
  std::uint32_t interfaces_ = 0;
};

}  // namespace sms::protocol::pcapng
