// Frame descriptions for the bus monitor (modbus_map/frame_description.h), on the example frames
// of Feetech's SCS communication protocol manual (PING, READ, WRITE, REG WRITE, ACTION, SYNC WRITE,
// SYNC READ and their answers, byte for byte as the manual prints them) and on the Modbus
// specification's RTU examples: frames our encoder did not make.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "modbus_map/frame_description.h"
#include "modbus_map/tables.h"
#include "protocol/instructions.h"
#include "protocol/modbus_rtu.h"

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;
using protocol::Bytes;

Bytes hex(const std::string& text) {
  Bytes bytes;
  for (std::size_t at = 0; at < text.size();) {
    if (text[at] == ' ') {
      ++at;
      continue;
    }
    bytes.push_back(static_cast<std::uint8_t>(std::stoi(text.substr(at, 2), nullptr, 16)));
    at += 2;
  }
  return bytes;
}

ServoTables sts_servos(std::initializer_list<std::uint8_t> ids) {
  ServoTables tables;
  for (const auto id : ids) tables.set(id, table(TableId::Sts), ByteOrder::LowFirst);
  return tables;
}

// One frame out of `bytes`, which must make exactly one.
FrameDescription one(FrameDescriber& describer, WireDirection direction, const std::string& bytes) {
  auto frames = describer.feed(direction, hex(bytes));
  EXPECT_EQ(frames.size(), 1u) << bytes;
  return frames.empty() ? FrameDescription{} : frames.front();
}

FrameDescription one(FrameDescriber& describer, WireDirection direction, const Bytes& bytes) {
  auto frames = describer.feed(direction, bytes);
  EXPECT_EQ(frames.size(), 1u);
  return frames.empty() ? FrameDescription{} : frames.front();
}

std::vector<std::string> names(const FrameDescription& frame) {
  std::vector<std::string> out;
  for (const auto& field : frame.fields) out.push_back(field.name);
  return out;
}

TEST(FrameDescription, ManualPingAndItsAnswer) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto ping = one(describer, WireDirection::ToServos, "FF FF 01 02 01 FB");
  EXPECT_EQ(ping.kind, FrameKind::Request);
  EXPECT_EQ(ping.instruction, "PING");
  EXPECT_EQ(ping.servo, 1);
  EXPECT_EQ(ping.bytes, hex("FF FF 01 02 01 FB"));
  const auto answer = one(describer, WireDirection::FromServos, "FF FF 01 02 00 FC");
  EXPECT_EQ(answer.kind, FrameKind::Answer);
  EXPECT_EQ(answer.instruction, "PING");
  EXPECT_EQ(answer.status, 0);
  EXPECT_TRUE(answer.status_bits.empty());
}

TEST(FrameDescription, ManualReadNamesTheFieldAndItsAnswerCarriesTheValue) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto read = one(describer, WireDirection::ToServos, "FF FF 01 04 02 38 02 BE");
  EXPECT_EQ(read.instruction, "READ");
  ASSERT_EQ(names(read), std::vector<std::string>{"present_position"});
  EXPECT_EQ(read.fields[0].address, 56);
  EXPECT_FALSE(read.fields[0].value);
  // The answer arrives in pieces, as from a USB adapter: one frame all the same.
  EXPECT_TRUE(describer.feed(WireDirection::FromServos, hex("FF FF 01")).empty());
  EXPECT_TRUE(describer.feed(WireDirection::FromServos, hex("04 00 18")).empty());
  const auto answer = one(describer, WireDirection::FromServos, "05 DD");
  EXPECT_EQ(answer.instruction, "READ");
  ASSERT_EQ(names(answer), std::vector<std::string>{"present_position"});
  EXPECT_EQ(answer.fields[0].value, 1304);  // the manual: 0x0518 = 1304
  EXPECT_EQ(answer.bytes, hex("FF FF 01 04 00 18 05 DD"));
}

TEST(FrameDescription, ManualWriteOfPositionTimeAndSpeed) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto write = one(describer, WireDirection::ToServos, "FF FF 01 09 03 2A 00 08 00 00 E8 03 D5");
  EXPECT_EQ(write.instruction, "WRITE");
  EXPECT_EQ(write.code, 0x03);
  ASSERT_EQ(names(write), (std::vector<std::string>{"goal_position", "goal_time", "goal_speed"}));
  EXPECT_EQ(write.fields[0].value, 2048);
  EXPECT_EQ(write.fields[1].value, 0);
  EXPECT_EQ(write.fields[2].value, 1000);
  const auto answer = one(describer, WireDirection::FromServos, "FF FF 01 02 00 FC");
  EXPECT_EQ(answer.instruction, "WRITE");
  EXPECT_EQ(answer.servo, 1);
}

TEST(FrameDescription, ManualRegWriteAndAction) {
  const auto tables = sts_servos({1, 2});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto staged = one(describer, WireDirection::ToServos, "FF FF 02 09 04 2A 00 08 00 00 E8 03 D3");
  EXPECT_EQ(staged.instruction, "REG WRITE");
  EXPECT_EQ(staged.servo, 2);
  EXPECT_EQ(staged.fields.at(0).value, 2048);
  const auto action = one(describer, WireDirection::ToServos, "FF FF FE 02 05 FA");
  EXPECT_EQ(action.instruction, "ACTION");
  EXPECT_EQ(action.servo, 0xFE);
  EXPECT_FALSE(action.retry);
}

TEST(FrameDescription, ManualSyncWriteNamesEveryServosFields) {
  const auto tables = sts_servos({1, 2, 3, 4});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto sync = one(describer, WireDirection::ToServos,
                        "FF FF FE 20 83 2A 06 01 00 08 00 00 E8 03 02 00 08 00 00 E8 03 03 00 08 00 00 E8 03 04 00 08 "
                        "00 00 E8 03 58");
  EXPECT_EQ(sync.instruction, "SYNC WRITE");
  EXPECT_EQ(sync.servos, (std::vector<std::uint8_t>{1, 2, 3, 4}));
  ASSERT_EQ(sync.fields.size(), 12u);
  EXPECT_EQ(sync.fields[3].name, "goal_position");
  EXPECT_EQ(sync.fields[3].servo, 2);
  EXPECT_EQ(sync.fields[3].value, 2048);
  EXPECT_EQ(sync.fields[11].name, "goal_speed");
  EXPECT_EQ(sync.fields[11].value, 1000);
}

TEST(FrameDescription, ManualSyncReadAndEachServosAnswer) {
  const auto tables = sts_servos({1, 2});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  const auto sync = one(describer, WireDirection::ToServos, "FF FF FE 06 82 38 08 01 02 36");
  EXPECT_EQ(sync.instruction, "SYNC READ");
  EXPECT_EQ(sync.servos, (std::vector<std::uint8_t>{1, 2}));
  EXPECT_EQ(names(sync), (std::vector<std::string>{"present_position", "present_speed", "present_load",
                                                   "present_voltage", "present_temperature"}));
  // Both answers in one read.
  auto answers =
      describer.feed(WireDirection::FromServos,
                     hex("FF FF 01 0A 00 00 08 00 00 00 00 79 1E 55 FF FF 02 0A 00 FF 07 00 00 00 00 77 23 53"));
  ASSERT_EQ(answers.size(), 2u);
  EXPECT_EQ(answers[0].instruction, "SYNC READ");
  EXPECT_EQ(answers[0].servo, 1);
  EXPECT_EQ(answers[0].fields.at(0).value, 2048);
  EXPECT_EQ(answers[0].fields.at(3).value, 0x79);  // present_voltage
  EXPECT_EQ(answers[0].fields.at(4).value, 0x1E);  // present_temperature
  EXPECT_EQ(answers[1].servo, 2);
  EXPECT_EQ(answers[1].fields.at(0).value, 2047);
  EXPECT_EQ(answers[1].fields.at(4).value, 0x23);
}

TEST(FrameDescription, ChecksumErrorKeepsTheBytesAsReceivedAndTheNextFrameIsWhole) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  one(describer, WireDirection::ToServos, "FF FF 01 02 01 FB");
  auto frames = describer.feed(WireDirection::FromServos, hex("FF FF 01 02 00 FD FF FF 01 02 00 FC"));
  ASSERT_EQ(frames.size(), 2u);
  EXPECT_EQ(frames[0].kind, FrameKind::Damaged);
  EXPECT_EQ(frames[0].bytes, hex("FF FF 01 02 00 FD"));
  EXPECT_NE(frames[0].error.find("0xFD received, 0xFC expected"), std::string::npos) << frames[0].error;
  EXPECT_EQ(frames[1].kind, FrameKind::Answer);
}

TEST(FrameDescription, GarbageBeforeAFrameIsNoise) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  auto frames = describer.feed(WireDirection::FromServos, hex("00 12 FF FF 01 02 00 FC"));
  ASSERT_EQ(frames.size(), 2u);
  EXPECT_EQ(frames[0].kind, FrameKind::Noise);
  EXPECT_EQ(frames[0].error, "2 bytes that made no frame");
  EXPECT_EQ(frames[1].kind, FrameKind::Answer);
}

TEST(FrameDescription, TheSameRequestAgainWithoutAnAnswerIsARetry) {
  const auto tables = sts_servos({1});
  FrameDescriber describer(BusProtocol::Feetech, tables);
  EXPECT_FALSE(one(describer, WireDirection::ToServos, "FF FF 01 04 02 38 02 BE").retry);
  EXPECT_TRUE(one(describer, WireDirection::ToServos, "FF FF 01 04 02 38 02 BE").retry);
  one(describer, WireDirection::FromServos, "FF FF 01 04 00 18 05 DD");
  // Answered: the next poll of the same block is no retry.
  EXPECT_FALSE(one(describer, WireDirection::ToServos, "FF FF 01 04 02 38 02 BE").retry);
}

TEST(FrameDescription, StatusBitsAreNamedPerProtocol) {
  const auto tables = sts_servos({1});
  FrameDescriber feetech(BusProtocol::Feetech, tables);
  const auto overload = one(feetech, WireDirection::FromServos, "FF FF 01 02 20 DC");
  EXPECT_EQ(overload.status, 0x20);
  EXPECT_EQ(overload.status_bits, std::vector<std::string_view>{"overload"});

  ServoTables d55d_tables;
  d55d_tables.set(3, table(TableId::D55d), ByteOrder::LowFirst);
  FrameDescriber d55d(BusProtocol::D55d, d55d_tables);
  const auto refused = protocol::encode(protocol::kD55dFormat, protocol::status(3, 0x20));
  ASSERT_EQ(refused[0], 0xD5);
  auto frames = d55d.feed(WireDirection::FromServos, refused);
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].status_bits, std::vector<std::string_view>{"instruction"});
  const auto write = protocol::encode(protocol::kD55dFormat, protocol::ping(3));
  frames = d55d.feed(WireDirection::ToServos, write);
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].instruction, "PING");
}

TEST(FrameDescription, ModbusRtuSpecificationExamples) {
  ServoTables tables;
  tables.set(1, table(TableId::Smsmb), ByteOrder::HighFirst);
  FrameDescriber describer(BusProtocol::ModbusRtu, tables);
  // Modbus over serial line: read 10 holding registers from 0 of slave 1, CRC C5 CD.
  const auto read = one(describer, WireDirection::ToServos, "01 03 00 00 00 0A C5 CD");
  EXPECT_EQ(read.kind, FrameKind::Request);
  EXPECT_EQ(read.instruction, "read_holding_registers");
  EXPECT_EQ(read.servo, 1);
  EXPECT_EQ(read.fields.front().name, "firmware_version");
  // An exception answer (illegal data address), CRC C0 F1.
  const auto refused = one(describer, WireDirection::FromServos, "01 83 02 C0 F1");
  EXPECT_EQ(refused.kind, FrameKind::Answer);
  EXPECT_EQ(refused.instruction, "read_holding_registers");
  EXPECT_EQ(refused.error, "exception 0x02 illegal data address");
  // A damaged CRC.
  const auto damaged = one(describer, WireDirection::FromServos, "01 83 02 C0 F2");
  EXPECT_EQ(damaged.kind, FrameKind::Damaged);
  EXPECT_EQ(damaged.error, "CRC error");
}

TEST(FrameDescription, ModbusRtuWriteAndReadNameSmsmbRegisters) {
  ServoTables tables;
  tables.set(1, table(TableId::Smsmb), ByteOrder::HighFirst);
  FrameDescriber describer(BusProtocol::ModbusRtu, tables);
  const Bytes write_frame = protocol::rtu::frame(1, Bytes{0x06, 0x00, 0x80, 0x0B, 0xB8});  // goal_position := 3000
  const auto write = one(describer, WireDirection::ToServos, write_frame);
  EXPECT_EQ(write.instruction, "write_single_register");
  ASSERT_EQ(write.fields.size(), 1u);
  EXPECT_EQ(write.fields[0].name, "goal_position");
  EXPECT_EQ(write.fields[0].value, 3000);
  const auto echo = one(describer, WireDirection::FromServos, write_frame);
  EXPECT_EQ(echo.kind, FrameKind::Answer);
  EXPECT_EQ(echo.fields.at(0).value, 3000);
  // A read of present_position (register 0x101) and its answer, arriving with a second frame
  // in the same piece: split by the function's length rule.
  one(describer, WireDirection::ToServos, protocol::rtu::frame(1, Bytes{0x03, 0x01, 0x01, 0x00, 0x01}));
  Bytes two = protocol::rtu::frame(1, Bytes{0x03, 0x02, 0x0B, 0xB7});
  const Bytes next = protocol::rtu::frame(2, Bytes{0x06, 0x00, 0x81, 0x00, 0x01});
  two.insert(two.end(), next.begin(), next.end());
  const auto frames = describer.feed(WireDirection::FromServos, two);
  ASSERT_EQ(frames.size(), 2u);
  ASSERT_EQ(frames[0].fields.size(), 1u);
  EXPECT_EQ(frames[0].fields[0].name, "present_position");
  EXPECT_EQ(frames[0].fields[0].value, 2999);
  EXPECT_EQ(frames[1].servo, 2);
  EXPECT_EQ(frames[1].kind, FrameKind::Answer);
}

}  // namespace
}  // namespace sms::modbus_map
