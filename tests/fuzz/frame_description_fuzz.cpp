// libFuzzer target: modbus_map::FrameDescriber, the bus monitor's decoder (docs/MONITOR.md), on
// every bus protocol. Input: fuzz_support.h's chunked layout, whose STREAM's first byte picks the
// protocol (mod 3: feetech, d55d, modbus-rtu); the boundary op turns the line around (the next
// pieces come from the other direction).
//
// Invariants, for every frame described:
//   - a request or an answer is a whole valid frame: its bytes decode again (packet: checksum
//     valid, LEN matching; RTU: CRC valid) and it names its servo;
//   - a damaged frame or noise says what is wrong; only noise may come without bytes;
//   - no field names an address outside what the frame covers by more than a field's size.
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "fuzz_support.h"
#include "modbus_map/frame_description.h"
#include "modbus_map/tables.h"
#include "protocol/modbus_rtu.h"
#include "protocol/packet.h"

namespace {

using sms::modbus_map::FrameDescription;
using sms::modbus_map::FrameKind;
using sms::modbus_map::WireDirection;
using sms::protocol::BusProtocol;

bool packet_frame_valid(const sms::protocol::PacketFormat& format, const sms::protocol::Bytes& bytes) {
  if (bytes.size() < sms::protocol::kMinFrameSize) return false;
  if (bytes[0] != format.header[0] || bytes[1] != format.header[1]) return false;
  if (bytes[3] + 4u != bytes.size()) return false;
  const auto body = std::span<const std::uint8_t>(bytes).subspan(2, bytes.size() - 3);
  return sms::protocol::checksum(format, body) == bytes.back();
}

bool rtu_frame_valid(const sms::protocol::Bytes& bytes) {
  if (bytes.size() < sms::protocol::rtu::kMinAduSize) return false;
  const auto body = std::span<const std::uint8_t>(bytes).first(bytes.size() - 2);
  return sms::protocol::rtu::crc16(body) ==
         static_cast<std::uint16_t>(bytes[bytes.size() - 2] | bytes[bytes.size() - 1] << 8);
}

void check(BusProtocol protocol, const FrameDescription& frame) {
  using sms::fuzz::hex;
  switch (frame.kind) {
    case FrameKind::Request:
    case FrameKind::Answer:
      SMS_FUZZ_CHECK(frame.servo.has_value(), "a frame without a servo: " + hex(frame.bytes));
      SMS_FUZZ_CHECK(frame.error.empty() || protocol == BusProtocol::ModbusRtu,
                     "a packet frame taken whole with an error: " + frame.error);
      if (protocol == BusProtocol::ModbusRtu) {
        SMS_FUZZ_CHECK(rtu_frame_valid(frame.bytes), "an RTU frame with a bad CRC taken whole: " + hex(frame.bytes));
      } else {
        const auto& format = protocol == BusProtocol::D55d ? sms::protocol::kD55dFormat : sms::protocol::kFeetechFormat;
        SMS_FUZZ_CHECK(packet_frame_valid(format, frame.bytes), "an invalid packet taken whole: " + hex(frame.bytes));
      }
      break;
    case FrameKind::Damaged:
      SMS_FUZZ_CHECK(!frame.error.empty(), "a damaged frame that does not say why: " + hex(frame.bytes));
      SMS_FUZZ_CHECK(!frame.bytes.empty(), "a damaged frame without bytes");
      break;
    case FrameKind::Noise: SMS_FUZZ_CHECK(!frame.error.empty(), "noise that does not say how much"); break;
  }
  for (const auto& field : frame.fields) SMS_FUZZ_CHECK(!field.name.empty(), "a field without a name");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  auto input = sms::fuzz::split_chunked_input(std::span(data, size));
  if (input.stream.empty()) return 0;
  const auto protocol = static_cast<BusProtocol>(input.stream[0] % 3);
  input.stream = input.stream.subspan(1);
  sms::modbus_map::ServoTables tables;
  // Servos 1-3 with the protocol's tables; every other ID unknown (fields by address).
  const auto table_id = protocol == BusProtocol::ModbusRtu ? sms::modbus_map::TableId::Smsmb
                        : protocol == BusProtocol::D55d    ? sms::modbus_map::TableId::D55d
                                                           : sms::modbus_map::TableId::Sts;
  const auto& table = sms::modbus_map::table(table_id);
  for (std::uint8_t id = 1; id <= 3; ++id) tables.set(id, table, table.default_byte_order);
  sms::modbus_map::FrameDescriber describer(protocol, tables);
  WireDirection direction = WireDirection::ToServos;
  sms::fuzz::play_chunked(
      input,
      [&](std::span<const std::uint8_t> chunk) {
        for (const auto& frame : describer.feed(direction, chunk)) check(protocol, frame);
      },
      [&] { direction = direction == WireDirection::ToServos ? WireDirection::FromServos : WireDirection::ToServos; });
  return 0;
}
