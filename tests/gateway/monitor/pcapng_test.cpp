// The pcapng writer (protocol/pcapng.h) block by block, against the pcapng specification's
// layout: tshark reading real captures is tests/gateway/monitor/tshark_test.sh.
#include <gtest/gtest.h>

#include <cstdint>
#include <string>

#include "gateway/bus/wire_monitor.h"
#include "modbus_map/tables.h"
#include "protocol/pcapng.h"

namespace sms::protocol::pcapng {
namespace {

std::uint32_t u32(const Bytes& bytes, std::size_t at) {
  return bytes[at] | bytes[at + 1] << 8 | bytes[at + 2] << 16 | static_cast<std::uint32_t>(bytes[at + 3]) << 24;
}
std::uint16_t u16(const Bytes& bytes, std::size_t at) {
  return static_cast<std::uint16_t>(bytes[at] | bytes[at + 1] << 8);
}

struct Block {
  std::uint32_t type;
  std::size_t start;
  std::uint32_t length;
};
std::vector<Block> blocks(const Bytes& file) {
  std::vector<Block> out;
  for (std::size_t at = 0; at < file.size();) {
    const std::uint32_t length = u32(file, at + 4);
    EXPECT_EQ(length % 4, 0u);
    EXPECT_EQ(u32(file, at + length - 4), length) << "trailing length of the block at " << at;
    out.push_back({u32(file, at), at, length});
    at += length;
  }
  return out;
}

TEST(Pcapng, SectionInterfaceAndPacketBlocks) {
  Writer writer("test");
  EXPECT_EQ(writer.add_interface(kLinkTypePacketBus, "arm", "bus arm"), 0u);
  const Bytes frame{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB};
  writer.add_packet(0, 1'700'000'000'123'456ULL, Direction::Outbound, frame);
  writer.add_packet(0, 1'700'000'000'124'000ULL, Direction::Inbound, frame, "checksum error");
  const Bytes file = writer.take();
  const auto found = blocks(file);
  ASSERT_EQ(found.size(), 4u);
  EXPECT_EQ(found[0].type, 0x0A0D0D0Au);
  EXPECT_EQ(u32(file, 8), 0x1A2B3C4Du);  // byte-order magic
  EXPECT_EQ(u16(file, 12), 1);           // version 1.0
  EXPECT_EQ(found[1].type, 1u);
  EXPECT_EQ(u16(file, found[1].start + 8), 147);  // LINKTYPE_USER0
  EXPECT_EQ(found[2].type, 6u);
  const std::size_t epb = found[2].start;
  EXPECT_EQ(u32(file, epb + 8), 0u);  // interface
  const std::uint64_t time = static_cast<std::uint64_t>(u32(file, epb + 12)) << 32 | u32(file, epb + 16);
  EXPECT_EQ(time, 1'700'000'000'123'456ULL);
  EXPECT_EQ(u32(file, epb + 20), 6u);
  EXPECT_EQ(u32(file, epb + 24), 6u);
  EXPECT_EQ(Bytes(file.begin() + epb + 28, file.begin() + epb + 34), frame);
  // After the 6 bytes padded to 8: epb_flags (2), length 4, value 2 = outbound.
  EXPECT_EQ(u16(file, epb + 36), 2);
  EXPECT_EQ(u16(file, epb + 38), 4);
  EXPECT_EQ(u32(file, epb + 40), 2u);
  const std::size_t second = found[3].start;
  EXPECT_EQ(u32(file, second + 40), 1u);  // inbound
  EXPECT_EQ(u16(file, second + 44), 1);   // opt_comment
  EXPECT_EQ(std::string(file.begin() + second + 48, file.begin() + second + 48 + 14), "checksum error");
}

TEST(Pcapng, AMonitorsCaptureHasOnePacketPerFrame) {
  modbus_map::ServoTables tables;
  tables.set(1, modbus_map::table(modbus_map::TableId::Smsmb), modbus_map::ByteOrder::HighFirst);
  gateway::WireMonitor monitor("lift", BusProtocol::ModbusRtu, tables, 64);
  // Request and answer, the answer read in two pieces.
  monitor.record(gateway::WireDirection::ToServos, Bytes{0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD});
  monitor.record(gateway::WireDirection::FromServos, Bytes{0x01, 0x83});
  monitor.record(gateway::WireDirection::FromServos, Bytes{0x02, 0xC0, 0xF1});
  const Bytes file = monitor.pcapng();
  const auto found = blocks(file);
  // Section, interface, and one packet per frame: the answer's pieces are joined again.
  ASSERT_EQ(found.size(), 4u);
  EXPECT_EQ(u16(file, found[1].start + 8), 148);  // LINKTYPE_USER1: Modbus RTU
  EXPECT_EQ(u32(file, found[3].start + 20), 5u);  // 01 83 02 C0 F1
  EXPECT_EQ(u32(file, found[3].start + 40), 1u);  // inbound
}

}  // namespace
}  // namespace sms::protocol::pcapng
