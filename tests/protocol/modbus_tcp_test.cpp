#include "protocol/modbus_tcp.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <stdexcept>
#include <variant>
#include <vector>

namespace sms::protocol::tcp {
namespace {

// Read holding registers 0x006B..0x006D of unit 0x11, transaction 1 (the classic example
// of the Modbus TCP implementation guide).
const Bytes kReadRequest{0x00, 0x01, 0x00, 0x00, 0x00, 0x06, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03};
const Bytes kReadRequestPdu{0x03, 0x00, 0x6B, 0x00, 0x03};
// Write single register 0x0080 = 0x0800 on unit 2, transaction 0xBEEF.
const Bytes kWriteRequest{0xBE, 0xEF, 0x00, 0x00, 0x00, 0x06, 0x02, 0x06, 0x00, 0x80, 0x08, 0x00};
const Bytes kWriteRequestPdu{0x06, 0x00, 0x80, 0x08, 0x00};

std::vector<MbapEvent> drain(MbapDecoder& decoder) {
  std::vector<MbapEvent> events;
  while (auto event = decoder.next()) events.push_back(std::move(*event));
  return events;
}

const Frame& as_frame(const MbapEvent& event) {
  EXPECT_TRUE(std::holds_alternative<Frame>(event));
  return std::get<Frame>(event);
}

TEST(MbapDecoder, DecodesOneRequest) {
  MbapDecoder decoder;
  decoder.feed(kReadRequest);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 1U);
  const Frame& frame = as_frame(events[0]);
  EXPECT_EQ(frame.transaction_id, 0x0001);
  EXPECT_EQ(frame.protocol_id, 0x0000);
  EXPECT_EQ(frame.unit_id, 0x11);
  EXPECT_EQ(frame.pdu, kReadRequestPdu);
  EXPECT_EQ(decoder.buffered(), 0U);
  EXPECT_FALSE(decoder.failed());
}

TEST(MbapDecoder, DecodesRequestSplitAtEveryByte) {
  for (std::size_t split = 0; split <= kReadRequest.size(); ++split) {
    MbapDecoder decoder;
    decoder.feed(std::span(kReadRequest).first(split));
    if (split < kReadRequest.size()) {
      EXPECT_FALSE(decoder.next().has_value()) << "split at " << split;
    }
    decoder.feed(std::span(kReadRequest).subspan(split));
    auto events = drain(decoder);
    ASSERT_EQ(events.size(), 1U) << "split at " << split;
    EXPECT_EQ(as_frame(events[0]).pdu, kReadRequestPdu) << "split at " << split;
    EXPECT_EQ(decoder.buffered(), 0U);
  }
}

TEST(MbapDecoder, DecodesRequestFedOneByteAtATime) {
  MbapDecoder decoder;
  std::vector<MbapEvent> events;
  for (std::size_t i = 0; i < kReadRequest.size(); ++i) {
    decoder.feed(std::span(kReadRequest).subspan(i, 1));
    auto more = drain(decoder);
    if (i + 1 < kReadRequest.size()) {
      EXPECT_TRUE(more.empty()) << "after byte " << i;
    }
    events.insert(events.end(), more.begin(), more.end());
  }
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(as_frame(events[0]).transaction_id, 0x0001);
}

TEST(MbapDecoder, DecodesTwoPipelinedRequestsInOneChunk) {
  Bytes both = kReadRequest;
  both.insert(both.end(), kWriteRequest.begin(), kWriteRequest.end());
  MbapDecoder decoder;
  decoder.feed(both);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(as_frame(events[0]).transaction_id, 0x0001);
  EXPECT_EQ(as_frame(events[0]).pdu, kReadRequestPdu);
  EXPECT_EQ(as_frame(events[1]).transaction_id, 0xBEEF);
  EXPECT_EQ(as_frame(events[1]).unit_id, 0x02);
  EXPECT_EQ(as_frame(events[1]).pdu, kWriteRequestPdu);
}

TEST(MbapDecoder, DecodesPipelinedRequestsSplitAtEveryByte) {
  Bytes both = kReadRequest;
  both.insert(both.end(), kWriteRequest.begin(), kWriteRequest.end());
  for (std::size_t split = 0; split <= both.size(); ++split) {
    MbapDecoder decoder;
    decoder.feed(std::span(both).first(split));
    auto events = drain(decoder);
    decoder.feed(std::span(both).subspan(split));
    auto rest = drain(decoder);
    events.insert(events.end(), rest.begin(), rest.end());
    ASSERT_EQ(events.size(), 2U) << "split at " << split;
    EXPECT_EQ(as_frame(events[0]).transaction_id, 0x0001) << "split at " << split;
    EXPECT_EQ(as_frame(events[1]).transaction_id, 0xBEEF) << "split at " << split;
  }
}

TEST(MbapDecoder, WaitsForTheWholePduTheLengthFieldAnnounces) {
  // Length 6 announces 5 PDU bytes; only 3 arrived.
  const Bytes partial{0x00, 0x07, 0x00, 0x00, 0x00, 0x06, 0x01, 0x03, 0x00, 0x6B};
  MbapDecoder decoder;
  decoder.feed(partial);
  EXPECT_FALSE(decoder.next().has_value());
  EXPECT_FALSE(decoder.failed());
  EXPECT_EQ(decoder.buffered(), 10U);
}

void expect_bad_header(const Bytes& bytes, std::uint16_t transaction_id, const std::string& mentions) {
  MbapDecoder decoder;
  decoder.feed(bytes);
  auto event = decoder.next();
  ASSERT_TRUE(event.has_value());
  ASSERT_TRUE(std::holds_alternative<BadHeader>(*event));
  const auto& bad = std::get<BadHeader>(*event);
  EXPECT_EQ(bad.transaction_id, transaction_id);
  EXPECT_TRUE(bad.close_connection);
  EXPECT_NE(bad.reason.find(mentions), std::string::npos) << bad.reason;
  EXPECT_NE(bad.reason.find("close the connection"), std::string::npos) << bad.reason;
  EXPECT_TRUE(decoder.failed());
  // Nothing after a bad header is trusted, not even a well-formed request.
  decoder.feed(kReadRequest);
  EXPECT_FALSE(decoder.next().has_value());
}

TEST(MbapDecoder, RejectsNonZeroProtocolId) {
  expect_bad_header({0x00, 0x05, 0x00, 0x01, 0x00, 0x06, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03}, 0x0005, "protocol id 1");
}

TEST(MbapDecoder, RejectsLengthFieldWithoutFunctionCode) {
  expect_bad_header({0x00, 0x06, 0x00, 0x00, 0x00, 0x01, 0x11}, 0x0006, "length field 1");
  expect_bad_header({0x00, 0x06, 0x00, 0x00, 0x00, 0x00, 0x11}, 0x0006, "length field 0");
}

TEST(MbapDecoder, RejectsLengthFieldBeyondTheLargestPdu) {
  // 255 = unit id + 254-byte PDU: one too many. Judged at once, without waiting for the body.
  expect_bad_header({0x12, 0x34, 0x00, 0x00, 0x00, 0xFF, 0x11}, 0x1234, "length field 255");
  expect_bad_header({0x12, 0x34, 0x00, 0x00, 0xFF, 0xFF, 0x11}, 0x1234, "length field 65535");
}

TEST(MbapDecoder, AcceptsTheLargestPdu) {
  Bytes adu{0x00, 0x09, 0x00, 0x00, 0x00, 0xFE, 0x01};  // length 254: unit + 253-byte PDU
  adu.push_back(0x10);
  adu.insert(adu.end(), 252, 0xA5);
  MbapDecoder decoder;
  decoder.feed(adu);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(as_frame(events[0]).pdu.size(), 253U);
  EXPECT_EQ(as_frame(events[0]).pdu.front(), 0x10);
  EXPECT_EQ(as_frame(events[0]).pdu.back(), 0xA5);
}

TEST(MbapDecoder, ShortLyingLengthMakesTheRestABadHeader) {
  // Length 3 claims a 2-byte PDU (03 00); the request really carried 5. The leftover
  // `6B 00 03 ...` is read as the next header: protocol id 0x0300 -> BadHeader.
  const Bytes lying{0x00, 0x01, 0x00, 0x00, 0x00, 0x03, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x00, 0x00, 0x00, 0x06};
  MbapDecoder decoder;
  decoder.feed(lying);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(as_frame(events[0]).pdu, (Bytes{0x03, 0x00}));
  ASSERT_TRUE(std::holds_alternative<BadHeader>(events[1]));
  EXPECT_EQ(std::get<BadHeader>(events[1]).transaction_id, 0x6B00);
  EXPECT_NE(std::get<BadHeader>(events[1]).reason.find("protocol id 768"), std::string::npos);
}

TEST(MbapDecoder, ResetClearsTheFailure) {
  MbapDecoder decoder;
  decoder.feed(Bytes{0x00, 0x01, 0x00, 0x02, 0x00, 0x06, 0x11});
  ASSERT_TRUE(decoder.next().has_value());
  ASSERT_TRUE(decoder.failed());
  decoder.reset();
  EXPECT_FALSE(decoder.failed());
  EXPECT_EQ(decoder.buffered(), 0U);
  decoder.feed(kWriteRequest);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(as_frame(events[0]).pdu, kWriteRequestPdu);
}

TEST(MbapDecoder, BufferDoesNotGrowAcrossManyRequests) {
  MbapDecoder decoder;
  for (int i = 0; i < 1000; ++i) {
    decoder.feed(kReadRequest);
    ASSERT_TRUE(decoder.next().has_value());
    EXPECT_EQ(decoder.buffered(), 0U);
  }
}

TEST(MbapDecoder, RandomBytesNeverCrashAndStopAtTheFirstBadHeader) {
  std::mt19937 random(99);
  for (int trial = 0; trial < 500; ++trial) {
    Bytes stream(random() % 300);
    for (auto& byte : stream) byte = static_cast<std::uint8_t>(random());
    if (trial % 2 == 0 && stream.size() >= 6) {
      stream[2] = stream[3] = stream[4] = 0x00;  // protocol id 0, plausible length
      stream[5] = static_cast<std::uint8_t>(2 + random() % 20);
    }
    MbapDecoder decoder;
    std::size_t offset = 0;
    std::size_t consumed = 0;
    bool failed = false;
    while (offset < stream.size()) {
      const std::size_t size = std::min<std::size_t>(1 + random() % 13, stream.size() - offset);
      decoder.feed(std::span(stream).subspan(offset, size));
      offset += size;
      for (const auto& event : drain(decoder)) {
        ASSERT_FALSE(failed) << "an event after a BadHeader, trial " << trial;
        if (std::holds_alternative<BadHeader>(event)) {
          failed = true;
        } else {
          const auto& frame = std::get<Frame>(event);
          EXPECT_GE(frame.pdu.size(), 1U);
          EXPECT_LE(frame.pdu.size(), kMaxPduSize);
          consumed += kMbapHeaderSize + frame.pdu.size();
        }
      }
    }
    EXPECT_EQ(decoder.failed(), failed);
    if (!failed) {
      EXPECT_EQ(consumed + decoder.buffered(), stream.size()) << "trial " << trial;
      EXPECT_LT(decoder.buffered(), kMaxAduSize);
    }
  }
}

TEST(MbapEncoder, EncodesHeaderBigEndianWithLengthOfUnitPlusPdu) {
  EXPECT_EQ(encode_mbap(0x0001, 0x11, kReadRequestPdu), kReadRequest);
  EXPECT_EQ(encode_mbap(0xBEEF, 0x02, kWriteRequestPdu), kWriteRequest);
  // FC03 response of two registers 0x1234, 0x5678 to unit 255, transaction 0x0102.
  EXPECT_EQ(encode_mbap(0x0102, 0xFF, Bytes{0x03, 0x04, 0x12, 0x34, 0x56, 0x78}),
            (Bytes{0x01, 0x02, 0x00, 0x00, 0x00, 0x07, 0xFF, 0x03, 0x04, 0x12, 0x34, 0x56, 0x78}));
}

TEST(MbapEncoder, EncodesAFrameAsItWasDecoded) {
  Frame frame{0xBEEF, 0, 0x02, kWriteRequestPdu};
  EXPECT_EQ(encode_mbap(frame), kWriteRequest);
}

TEST(MbapEncoder, RefusesEmptyAndOversizedPdus) {
  EXPECT_THROW(encode_mbap(1, 1, Bytes{}), std::length_error);
  EXPECT_THROW(encode_mbap(1, 1, Bytes(254, 0x03)), std::length_error);
  EXPECT_EQ(encode_mbap(1, 1, Bytes(253, 0x03)).size(), 260U);
}

TEST(ModbusPdu, ExceptionPduSetsBit7OfTheFunction) {
  EXPECT_EQ(exception_pdu(0x03, exception_code::kIllegalDataAddress), (Bytes{0x83, 0x02}));
  EXPECT_EQ(exception_pdu(0x10, exception_code::kGatewayTargetFailedToRespond), (Bytes{0x90, 0x0B}));
  EXPECT_EQ(exception_pdu(0x2B, exception_code::kIllegalFunction), (Bytes{0xAB, 0x01}));
}

TEST(ModbusPdu, ExceptionCodeOfReadsOnlyExceptionResponses) {
  EXPECT_EQ(exception_code_of(Bytes{0x86, 0x04}), std::optional<std::uint8_t>(0x04));
  EXPECT_EQ(exception_code_of(Bytes{0x06, 0x00, 0x80, 0x08, 0x00}), std::nullopt);
  EXPECT_EQ(exception_code_of(Bytes{0x83}), std::nullopt);
  EXPECT_EQ(exception_code_of(Bytes{}), std::nullopt);
}

}  // namespace
}  // namespace sms::protocol::tcp
