#include "protocol/modbus_rtu.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <string>
#include <vector>

namespace sms::protocol::rtu {
namespace {

using Kind = RequestDecoder::Event::Kind;

// docs/PROTOCOL.md §1.3 worked frames, and more requests whose CRCs were computed outside this code.
const Bytes kReadFeedback{0x01, 0x03, 0x01, 0x00, 0x00, 0x08, 0x45, 0xF0};
const Bytes kWriteGoal{0x01, 0x06, 0x00, 0x80, 0x08, 0x00, 0x8F, 0xE2};
const Bytes kWriteTwoRegisters{0x01, 0x10, 0x00, 0x80, 0x00, 0x02, 0x04, 0x08, 0x00, 0x00, 0x0A, 0x79, 0xA8};
const Bytes kReportSlaveId{0x01, 0x11, 0xC0, 0x2C};
const Bytes kRestart{0x01, 0x41, 0xC0, 0x10};
const Bytes kRestartEverySlave{0x00, 0x41, 0xC1, 0x80};
const Bytes kReadCoils{0x02, 0x01, 0x00, 0x00, 0x00, 0x10, 0x3D, 0xF5};
const Bytes kReadDiscreteInputs{0x02, 0x02, 0x00, 0x00, 0x00, 0x08, 0x79, 0xFF};
const Bytes kReadInputRegisters{0x02, 0x04, 0x01, 0x00, 0x00, 0x08, 0xF0, 0x03};
const Bytes kWriteCoil{0x02, 0x05, 0x00, 0x01, 0xFF, 0x00, 0xDD, 0xC9};
const Bytes kWriteCoils{0x02, 0x0F, 0x00, 0x00, 0x00, 0x0A, 0x02, 0x01, 0x03, 0xB0, 0x59};
const Bytes kReadWriteRegisters{0x01, 0x17, 0x01, 0x00, 0x00, 0x02, 0x00, 0x80,
                                0x00, 0x01, 0x02, 0x00, 0x0A, 0x8F, 0x80};
const Bytes kReadDeviceId{0x01, 0x2B, 0x0E, 0x01, 0x00, 0x70, 0x77};  // FC 0x2B: no length rule

std::vector<RequestDecoder::Event> drain(RequestDecoder& decoder) {
  std::vector<RequestDecoder::Event> events;
  while (auto event = decoder.next()) events.push_back(std::move(*event));
  return events;
}

Bytes concat(std::initializer_list<Bytes> parts) {
  Bytes out;
  for (const auto& part : parts) out.insert(out.end(), part.begin(), part.end());
  return out;
}

Adu adu_of(const Bytes& frame) { return Adu{frame[0], Bytes(frame.begin() + 1, frame.end() - 2)}; }

TEST(ModbusRtuCrc, MatchesTheWorkedFramesOfTheSpec) {
  EXPECT_EQ(crc16(Bytes{0x01, 0x03, 0x01, 0x00, 0x00, 0x08}), 0xF045);
  EXPECT_EQ(crc16(Bytes{0x01, 0x06, 0x00, 0x80, 0x08, 0x00}), 0xE28F);
  EXPECT_EQ(crc16(Bytes{}), 0xFFFF);
}

TEST(ModbusRtuFrame, AppendsCrcLowByteFirst) {
  EXPECT_EQ(frame(0x01, Bytes{0x03, 0x01, 0x00, 0x00, 0x08}), kReadFeedback);
  EXPECT_EQ(frame(0x01, Bytes{0x06, 0x00, 0x80, 0x08, 0x00}), kWriteGoal);
  EXPECT_EQ(frame(0x01, Bytes{0x11}), kReportSlaveId);
}

TEST(ModbusRtuRequestDecoder, DecodesEveryFunctionCodeByItsLength) {
  for (const Bytes* request :
       {&kReadFeedback, &kWriteGoal, &kWriteTwoRegisters, &kReportSlaveId, &kRestart, &kRestartEverySlave, &kReadCoils,
        &kReadDiscreteInputs, &kReadInputRegisters, &kWriteCoil, &kWriteCoils, &kReadWriteRegisters}) {
    const std::string context = "function " + std::to_string((*request)[1]);
    RequestDecoder decoder;
    // Byte by byte: the frame must come out exactly when its last byte arrives.
    for (std::size_t i = 0; i + 1 < request->size(); ++i) {
      decoder.feed(std::span(*request).subspan(i, 1));
      EXPECT_FALSE(decoder.next().has_value()) << context << " after byte " << i;
    }
    decoder.feed(std::span(*request).last(1));
    auto event = decoder.next();
    ASSERT_TRUE(event.has_value()) << context;
    EXPECT_EQ(event->kind, Kind::Frame) << context;
    EXPECT_EQ(event->adu, adu_of(*request)) << context;
    EXPECT_EQ(decoder.buffered(), 0U) << context;
  }
}

TEST(ModbusRtuRequestDecoder, DecodesTheSpecFramesIntoSlaveAndPdu) {
  RequestDecoder decoder;
  decoder.feed(concat({kReadFeedback, kWriteGoal}));
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].adu, (Adu{0x01, {0x03, 0x01, 0x00, 0x00, 0x08}}));
  EXPECT_EQ(events[1].adu, (Adu{0x01, {0x06, 0x00, 0x80, 0x08, 0x00}}));
}

TEST(ModbusRtuRequestDecoder, UnknownFunctionEndsAtSilence) {
  RequestDecoder decoder;
  decoder.feed(kReadDeviceId);
  EXPECT_FALSE(decoder.next().has_value());
  auto event = decoder.end_of_frame();
  ASSERT_TRUE(event.has_value());
  EXPECT_EQ(event->kind, Kind::Frame);
  EXPECT_EQ(event->adu, (Adu{0x01, {0x2B, 0x0E, 0x01, 0x00}}));
  EXPECT_EQ(decoder.buffered(), 0U);
}

TEST(ModbusRtuRequestDecoder, ReportsCrcErrorOnceAndFindsTheNextRequest) {
  Bytes corrupt = kWriteGoal;
  corrupt[4] ^= 0x01;  // goal 0x0900 instead of 0x0800
  RequestDecoder decoder;
  decoder.feed(concat({corrupt, kReadFeedback}));
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, Kind::CrcError);
  EXPECT_EQ(events[0].adu, (Adu{0x01, {0x06, 0x00, 0x80, 0x09, 0x00}}));
  EXPECT_EQ(events[1].kind, Kind::Frame);
  EXPECT_EQ(events[1].adu, adu_of(kReadFeedback));
  EXPECT_EQ(decoder.crc_errors(), 1U);
  EXPECT_EQ(decoder.discarded_bytes(), 8U);
}

TEST(ModbusRtuRequestDecoder, CrcErrorSplitAtEveryByteGivesTheSameEvents) {
  Bytes corrupt = kWriteTwoRegisters;
  corrupt[8] ^= 0x40;
  const Bytes stream = concat({corrupt, kReportSlaveId, kWriteGoal});
  for (std::size_t split = 0; split <= stream.size(); ++split) {
    RequestDecoder decoder;
    decoder.feed(std::span(stream).first(split));
    auto events = drain(decoder);
    decoder.feed(std::span(stream).subspan(split));
    auto rest = drain(decoder);
    events.insert(events.end(), rest.begin(), rest.end());
    ASSERT_EQ(events.size(), 3U) << "split at " << split;
    EXPECT_EQ(events[0].kind, Kind::CrcError);
    EXPECT_EQ(events[1].kind, Kind::Frame);
    EXPECT_EQ(events[1].adu, adu_of(kReportSlaveId));
    EXPECT_EQ(events[2].kind, Kind::Frame);
    EXPECT_EQ(events[2].adu, adu_of(kWriteGoal));
    EXPECT_EQ(decoder.crc_errors(), 1U);
  }
}

TEST(ModbusRtuRequestDecoder, TailOfACorruptFrameIsNoiseAtSilence) {
  Bytes corrupt = kWriteTwoRegisters;
  corrupt[6] = 0x40;  // byte count 64: the frame claims bytes that never come
  RequestDecoder decoder;
  decoder.feed(corrupt);
  EXPECT_TRUE(drain(decoder).empty());
  auto event = decoder.end_of_frame();
  ASSERT_TRUE(event.has_value());
  EXPECT_EQ(event->kind, Kind::CrcError);
  EXPECT_EQ(decoder.crc_errors(), 1U);
  EXPECT_EQ(decoder.buffered(), 0U);
  // The next request after the silence decodes normally.
  decoder.feed(kWriteGoal);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
}

TEST(ModbusRtuRequestDecoder, ShortNoiseAtSilenceIsDroppedWithoutAnEvent) {
  RequestDecoder decoder;
  decoder.feed(Bytes{0x00, 0x7E, 0x11});
  EXPECT_FALSE(decoder.next().has_value());
  EXPECT_FALSE(decoder.end_of_frame().has_value());
  EXPECT_EQ(decoder.discarded_bytes(), 3U);
  EXPECT_EQ(decoder.crc_errors(), 0U);
}

TEST(ModbusRtuRequestDecoder, UnknownFunctionWithBadCrcAtSilenceIsACrcError) {
  Bytes corrupt = kReadDeviceId;
  corrupt.back() ^= 0xFF;
  RequestDecoder decoder;
  decoder.feed(corrupt);
  auto event = decoder.end_of_frame();
  ASSERT_TRUE(event.has_value());
  EXPECT_EQ(event->kind, Kind::CrcError);
  EXPECT_EQ(decoder.crc_errors(), 1U);
}

TEST(ModbusRtuRequestDecoder, NeverWaitsPastTheLargestAdu) {
  RequestDecoder decoder;
  // An unknown function code followed by endless bytes: no silence ever signalled.
  Bytes noise(1000, 0x00);
  noise[1] = 0x7E;
  decoder.feed(noise);
  drain(decoder);
  EXPECT_LE(decoder.buffered(), kMaxAduSize);
  // A byte count no request can carry (FC 0x10, 250 data bytes) is not waited for either.
  RequestDecoder counted;
  counted.feed(concat({{0x01, 0x10, 0x00, 0x80, 0x00, 0x7D, 0xFA}, kWriteGoal}));
  auto events = drain(counted);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
  EXPECT_EQ(events[0].adu, adu_of(kWriteGoal));
}

TEST(ModbusRtuRequestDecoder, RandomBytesNeverCrash) {
  std::mt19937 random(7);
  for (int trial = 0; trial < 300; ++trial) {
    RequestDecoder decoder;
    Bytes stream(random() % 600);
    for (auto& byte : stream) byte = static_cast<std::uint8_t>(random());
    if (trial % 3 == 0) stream.insert(stream.end(), kWriteGoal.begin(), kWriteGoal.end());
    std::size_t offset = 0;
    std::size_t frame_bytes = 0;
    while (offset < stream.size()) {
      const std::size_t size = std::min<std::size_t>(1 + random() % 40, stream.size() - offset);
      decoder.feed(std::span(stream).subspan(offset, size));
      offset += size;
      for (const auto& event : drain(decoder)) {
        if (event.kind == Kind::Frame) frame_bytes += event.adu.pdu.size() + 3;
      }
      EXPECT_LE(decoder.buffered(), kMaxAduSize + 40);
    }
    if (auto event = decoder.end_of_frame(); event && event->kind == Kind::Frame) {
      frame_bytes += event->adu.pdu.size() + 3;
    }
    EXPECT_EQ(decoder.buffered(), 0U);
    // Every byte was either part of a frame or discarded.
    EXPECT_EQ(frame_bytes + decoder.discarded_bytes(), stream.size()) << "trial " << trial;
  }
}

}  // namespace
}  // namespace sms::protocol::rtu
