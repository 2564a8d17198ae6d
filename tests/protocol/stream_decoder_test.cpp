#include "protocol/stream_decoder.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <random>
#include <string>
#include <utility>
#include <vector>

namespace sms::protocol {
namespace {

using Kind = DecodeEvent::Kind;

std::vector<DecodeEvent> drain(StreamDecoder& decoder) {
  std::vector<DecodeEvent> events;
  while (auto event = decoder.next()) events.push_back(std::move(*event));
  return events;
}

std::vector<DecodeEvent> decode_all(const PacketFormat& format, const Bytes& stream) {
  StreamDecoder decoder(format);
  decoder.feed(stream);
  return drain(decoder);
}

// Feeds `stream` in chunks whose sizes are taken from `chunk_sizes` cyclically.
std::vector<DecodeEvent> decode_chunked(StreamDecoder& decoder, const Bytes& stream,
                                        const std::vector<std::size_t>& chunk_sizes) {
  std::vector<DecodeEvent> events;
  std::size_t offset = 0;
  for (std::size_t i = 0; offset < stream.size(); ++i) {
    const std::size_t size = std::min(chunk_sizes[i % chunk_sizes.size()], stream.size() - offset);
    decoder.feed(std::span(stream).subspan(offset, size));
    offset += size;
    auto more = drain(decoder);
    events.insert(events.end(), more.begin(), more.end());
  }
  return events;
}

Bytes concat(std::initializer_list<Bytes> parts) {
  Bytes out;
  for (const auto& part : parts) out.insert(out.end(), part.begin(), part.end());
  return out;
}

void expect_same_events(const std::vector<DecodeEvent>& actual, const std::vector<DecodeEvent>& expected,
                        const std::string& context) {
  ASSERT_EQ(actual.size(), expected.size()) << context;
  for (std::size_t i = 0; i < actual.size(); ++i) {
    EXPECT_EQ(actual[i].kind, expected[i].kind) << context << ", event " << i;
    EXPECT_EQ(actual[i].packet, expected[i].packet) << context << ", event " << i;
    EXPECT_EQ(actual[i].skipped_before, expected[i].skipped_before) << context << ", event " << i;
  }
}

// docs/PROTOCOL.md §1.1 worked frames.
const Bytes kPingRequest{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB};
const Bytes kPingReply{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC};
const Bytes kReadReply{0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD};
const Bytes kWriteRequest{0xFF, 0xFF, 0x01, 0x09, 0x03, 0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03, 0xD5};
const Bytes kSyncReadReply1{0xFF, 0xFF, 0x01, 0x0A, 0x00, 0x00, 0x08, 0x00, 0x00, 0x00, 0x00, 0x79, 0x1E, 0x55};
const Bytes kSyncReadReply2{0xFF, 0xFF, 0x02, 0x0A, 0x00, 0xFF, 0x07, 0x00, 0x00, 0x00, 0x00, 0x77, 0x23, 0x53};

struct WorkedFrame {
  Bytes bytes;
  Packet packet;
};

TEST(FeetechDecoder, DecodesEveryWorkedFrameOfTheSpec) {
  const std::vector<WorkedFrame> frames{
      {kPingRequest, {0x01, 0x01, {}}},
      {kPingReply, {0x01, 0x00, {}}},
      {{0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE}, {0x01, 0x02, {0x38, 0x02}}},
      {kReadReply, {0x01, 0x00, {0x18, 0x05}}},
      {kWriteRequest, {0x01, 0x03, {0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03}}},
      {{0xFF, 0xFF, 0xFE, 0x02, 0x05, 0xFA}, {0xFE, 0x05, {}}},
      {{0xFF, 0xFF, 0xFE, 0x06, 0x82, 0x38, 0x08, 0x01, 0x02, 0x36}, {0xFE, 0x82, {0x38, 0x08, 0x01, 0x02}}},
      {kSyncReadReply1, {0x01, 0x00, {0x00, 0x08, 0x00, 0x00, 0x00, 0x00, 0x79, 0x1E}}},
      {kSyncReadReply2, {0x02, 0x00, {0xFF, 0x07, 0x00, 0x00, 0x00, 0x00, 0x77, 0x23}}},
      {{0xFF, 0xFF, 0x01, 0x02, 0x0A, 0xF2}, {0x01, 0x0A, {}}},
      {{0xFF, 0xFF, 0x01, 0x04, 0x0B, 0x00, 0x04, 0xEB}, {0x01, 0x0B, {0x00, 0x04}}},
  };
  for (const auto& frame : frames) {
    auto events = decode_all(kFeetechFormat, frame.bytes);
    ASSERT_EQ(events.size(), 1U);
    EXPECT_EQ(events[0].kind, Kind::Frame);
    EXPECT_EQ(events[0].packet, frame.packet);
    EXPECT_EQ(events[0].skipped_before, 0U);
  }
}

TEST(FeetechDecoder, DecodesBothSyncReadRepliesFromOneStream) {
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(concat({kSyncReadReply1, kSyncReadReply2}));
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
  EXPECT_EQ(events[0].packet.id, 0x01);
  EXPECT_EQ(events[0].packet.params, (Bytes{0x00, 0x08, 0x00, 0x00, 0x00, 0x00, 0x79, 0x1E}));
  EXPECT_EQ(events[1].kind, Kind::Frame);
  EXPECT_EQ(events[1].packet.id, 0x02);
  EXPECT_EQ(events[1].packet.params, (Bytes{0xFF, 0x07, 0x00, 0x00, 0x00, 0x00, 0x77, 0x23}));
  EXPECT_EQ(decoder.buffered(), 0U);
  EXPECT_EQ(decoder.discarded_bytes(), 0U);
}

TEST(D55dDecoder, DecodesTheWorkedExampleOfTheSpec) {
  auto events = decode_all(kD55dFormat, Bytes{0xD5, 0x5D, 0xFE, 0x04, 0x03, 0x03, 0x01, 0x09});
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
  EXPECT_EQ(events[0].packet, (Packet{0xFE, 0x03, {0x03, 0x01}}));
}

TEST(D55dDecoder, RejectsTheFeetechInvertedChecksum) {
  // The same frame with a feetech checksum (~0x09 = F6) is corrupt on a d55d bus.
  auto events = decode_all(kD55dFormat, Bytes{0xD5, 0x5D, 0xFE, 0x04, 0x03, 0x03, 0x01, 0xF6});
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].kind, Kind::ChecksumError);
}

TEST(D55dDecoder, AcceptsPingRepliesWithLen2And3) {
  // docs/PROTOCOL.md §1.2 decision: ERROR at byte 5, LEN 3 carries one parameter.
  auto events = decode_all(kD55dFormat, Bytes{0xD5, 0x5D, 0x01, 0x03, 0x01, 0x00, 0x05,  //
                                              0xD5, 0x5D, 0x01, 0x02, 0x00, 0x03});
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
  EXPECT_EQ(events[0].packet, (Packet{0x01, 0x01, {0x00}}));
  EXPECT_EQ(events[1].kind, Kind::Frame);
  EXPECT_EQ(events[1].packet, (Packet{0x01, 0x00, {}}));
}

// Garbage ending in a stray FF: `FF FF FF 01` must still find the frame at the second FF.
const Bytes kGarbage{0x00, 0x13, 0xFF, 0x42, 0xFE, 0x07, 0xFF};

TEST(FeetechDecoder, FindsFrameAfterGarbageSplitAtEveryByte) {
  const Bytes stream = concat({kGarbage, kReadReply});
  for (std::size_t split = 0; split <= stream.size(); ++split) {
    StreamDecoder decoder(kFeetechFormat);
    decoder.feed(std::span(stream).first(split));
    auto events = drain(decoder);
    decoder.feed(std::span(stream).subspan(split));
    auto rest = drain(decoder);
    events.insert(events.end(), rest.begin(), rest.end());
    ASSERT_EQ(events.size(), 1U) << "split at " << split;
    EXPECT_EQ(events[0].kind, Kind::Frame) << "split at " << split;
    EXPECT_EQ(events[0].packet, (Packet{0x01, 0x00, {0x18, 0x05}})) << "split at " << split;
    EXPECT_EQ(events[0].skipped_before, kGarbage.size()) << "split at " << split;
    EXPECT_EQ(decoder.discarded_bytes(), kGarbage.size());
    EXPECT_EQ(decoder.checksum_errors(), 0U);
    EXPECT_EQ(decoder.length_errors(), 0U);
    EXPECT_EQ(decoder.buffered(), 0U);
  }
}

TEST(FeetechDecoder, FindsFrameAfterGarbageFedOneTwoAndThreeBytesAtATime) {
  const Bytes stream = concat({kGarbage, kReadReply, kGarbage, kPingReply});
  for (std::size_t chunk : {1U, 2U, 3U}) {
    StreamDecoder decoder(kFeetechFormat);
    auto events = decode_chunked(decoder, stream, {chunk});
    ASSERT_EQ(events.size(), 2U) << "chunk " << chunk;
    EXPECT_EQ(events[0].packet, (Packet{0x01, 0x00, {0x18, 0x05}}));
    EXPECT_EQ(events[0].skipped_before, 7U);
    EXPECT_EQ(events[1].packet, (Packet{0x01, 0x00, {}}));
    EXPECT_EQ(events[1].skipped_before, 7U);
    EXPECT_EQ(decoder.discarded_bytes(), 14U);
  }
}

TEST(FeetechDecoder, DropsAStrayHeaderByteWithoutAnError) {
  auto events = decode_all(kFeetechFormat, Bytes{0xFF, 0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB});
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].kind, Kind::Frame);
  EXPECT_EQ(events[0].packet, (Packet{0x01, 0x01, {}}));
  EXPECT_EQ(events[0].skipped_before, 1U);
}

TEST(FeetechDecoder, ReportsChecksumErrorAndFindsTheNextFrame) {
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(Bytes{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFA,  // PING with CHK FA instead of FB
                     0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC});
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, Kind::ChecksumError);
  EXPECT_EQ(events[0].packet, (Packet{0x01, 0x01, {}}));  // what the corrupt frame said
  EXPECT_EQ(events[1].kind, Kind::Frame);
  EXPECT_EQ(events[1].packet, (Packet{0x01, 0x00, {}}));
  EXPECT_EQ(events[1].skipped_before, 6U);  // the whole corrupt frame
  EXPECT_EQ(decoder.checksum_errors(), 1U);
  EXPECT_EQ(decoder.discarded_bytes(), 6U);
}

TEST(FeetechDecoder, FindsAFrameThatStartsInsideATruncatedOne) {
  // A WRITE cut after 8 of its 13 bytes, then a whole PING: the WRITE's LEN swallows the
  // PING's first 5 bytes, its checksum fails, and the resync one byte past its header finds
  // the PING.
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(concat({Bytes(kWriteRequest.begin(), kWriteRequest.begin() + 8), kPingRequest}));
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, Kind::ChecksumError);
  EXPECT_EQ(events[0].packet, (Packet{0x01, 0x03, {0x2A, 0x00, 0x08, 0xFF, 0xFF, 0x01, 0x02}}));
  EXPECT_EQ(events[1].kind, Kind::Frame);
  EXPECT_EQ(events[1].packet, (Packet{0x01, 0x01, {}}));
  EXPECT_EQ(events[1].skipped_before, 8U);
  EXPECT_EQ(decoder.buffered(), 0U);
}

TEST(FeetechDecoder, ReportsLengthBelowTwoAndResyncs) {
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(Bytes{0xFF, 0xFF, 0x05, 0x01, 0x00,  // LEN 1
                     0xFF, 0xFF, 0x06, 0x00,        // LEN 0
                     0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC});
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 3U);
  EXPECT_EQ(events[0].kind, Kind::LengthError);
  EXPECT_EQ(events[0].packet.id, 0x05);
  EXPECT_EQ(events[1].kind, Kind::LengthError);
  EXPECT_EQ(events[1].packet.id, 0x06);
  EXPECT_EQ(events[1].skipped_before, 5U);
  EXPECT_EQ(events[2].kind, Kind::Frame);
  EXPECT_EQ(events[2].skipped_before, 4U);
  EXPECT_EQ(decoder.length_errors(), 2U);
  EXPECT_EQ(decoder.checksum_errors(), 0U);
  EXPECT_EQ(decoder.discarded_bytes(), 9U);
}

TEST(FeetechDecoder, ErrorEventsDoNotDependOnChunking) {
  const Bytes stream = concat({kGarbage,
                               {0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFA},  // checksum error
                               kSyncReadReply1,
                               {0xFF, 0xFF, 0x03, 0x01, 0x00},  // length error
                               Bytes(kWriteRequest.begin(), kWriteRequest.begin() + 8),
                               kSyncReadReply2});
  StreamDecoder reference(kFeetechFormat);
  reference.feed(stream);
  const auto expected = drain(reference);
  ASSERT_EQ(expected.size(), 5U);
  EXPECT_EQ(expected[0].kind, Kind::ChecksumError);
  EXPECT_EQ(expected[1].kind, Kind::Frame);
  EXPECT_EQ(expected[2].kind, Kind::LengthError);
  EXPECT_EQ(expected[3].kind, Kind::ChecksumError);
  EXPECT_EQ(expected[4].kind, Kind::Frame);
  EXPECT_EQ(expected[4].packet.id, 0x02);
  EXPECT_EQ(reference.checksum_errors(), 2U);
  EXPECT_EQ(reference.length_errors(), 1U);

  for (std::size_t first = 0; first <= stream.size(); ++first) {
    for (std::size_t second = first; second <= stream.size(); ++second) {
      StreamDecoder decoder(kFeetechFormat);
      std::vector<DecodeEvent> events;
      const std::array<std::pair<std::size_t, std::size_t>, 3> parts{
          {{0, first}, {first, second}, {second, stream.size()}}};
      for (const auto& [from, to] : parts) {
        decoder.feed(std::span(stream).subspan(from, to - from));
        auto more = drain(decoder);
        events.insert(events.end(), more.begin(), more.end());
      }
      expect_same_events(events, expected, "splits " + std::to_string(first) + "," + std::to_string(second));
      EXPECT_EQ(decoder.checksum_errors(), 2U);
      EXPECT_EQ(decoder.length_errors(), 1U);
      EXPECT_EQ(decoder.discarded_bytes(), reference.discarded_bytes());
    }
  }
}

TEST(FeetechDecoder, WaitsForTheWholeFrame) {
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(Bytes(kWriteRequest.begin(), kWriteRequest.end() - 1));
  EXPECT_FALSE(decoder.next().has_value());
  EXPECT_EQ(decoder.buffered(), kWriteRequest.size() - 1);
  decoder.feed(Bytes{kWriteRequest.back()});
  auto event = decoder.next();
  ASSERT_TRUE(event.has_value());
  EXPECT_EQ(event->kind, Kind::Frame);
}

TEST(FeetechDecoder, ResetDropsAndCountsBufferedBytes) {
  StreamDecoder decoder(kFeetechFormat);
  decoder.feed(Bytes{0xFF, 0xFF, 0x01, 0x04, 0x00});
  EXPECT_EQ(decoder.buffered(), 5U);
  decoder.reset();
  EXPECT_EQ(decoder.buffered(), 0U);
  EXPECT_EQ(decoder.discarded_bytes(), 5U);
  decoder.feed(kPingReply);
  auto events = drain(decoder);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].skipped_before, 0U);
}

TEST(FeetechDecoder, GarbageNeverAccumulates) {
  StreamDecoder decoder(kFeetechFormat);
  std::mt19937 random(1234);
  Bytes chunk(4096);
  for (int round = 0; round < 64; ++round) {
    for (auto& byte : chunk) byte = static_cast<std::uint8_t>(random() % 0xFF);  // never 0xFF
    decoder.feed(chunk);  // no next(): garbage alone must not pile up
    EXPECT_EQ(decoder.buffered(), 0U);
  }
  EXPECT_EQ(decoder.discarded_bytes(), 64U * 4096U);
  // A run of header bytes keeps at most a header's worth.
  decoder.feed(Bytes(1000, 0xFF));
  EXPECT_LE(decoder.buffered(), 2U);
}

TEST(D55dDecoder, FalseHeadersStayBoundedWhenDrained) {
  // `D5 5D` repeated looks like frames with LEN 0x5D; each fails and is resynced.
  StreamDecoder decoder(kD55dFormat);
  Bytes chunk;
  for (int i = 0; i < 512; ++i) chunk.insert(chunk.end(), {0xD5, 0x5D});
  for (int round = 0; round < 16; ++round) {
    decoder.feed(chunk);
    drain(decoder);
    EXPECT_LT(decoder.buffered(), StreamDecoder::kMaxFrameSize);
  }
  EXPECT_GT(decoder.checksum_errors(), 0U);
}

// Deterministic fuzz: valid frames, garbage and corrupted frames in random chunks. The
// decoder must not crash (ASan/UBSan watch), must account for every byte, must find every
// frame of a clean stream, and must not depend on the chunking.
TEST(StreamDecoderFuzz, RandomStreamsNeverCrashAndAccountForEveryByte) {
  std::mt19937 random(20240611);
  for (const PacketFormat* format : {&kFeetechFormat, &kD55dFormat}) {
    for (int trial = 0; trial < 200; ++trial) {
      Bytes stream;
      std::vector<Packet> clean_packets;
      bool clean = trial % 2 == 0;  // even trials: frames separated by header-free garbage only
      const int pieces = 1 + static_cast<int>(random() % 12);
      for (int piece = 0; piece < pieces; ++piece) {
        const auto choice = random() % 4;
        if (choice == 0 || clean) {
          Packet packet{static_cast<std::uint8_t>(random() % 0xFE), static_cast<std::uint8_t>(random()), {}};
          packet.params.resize(random() % 40);
          for (auto& byte : packet.params) byte = static_cast<std::uint8_t>(random());
          Bytes frame = encode(*format, packet);
          if (!clean && random() % 2 == 0)
            frame[random() % frame.size()] ^= static_cast<std::uint8_t>(1 + random() % 255);
          if (!clean && random() % 3 == 0) frame.resize(random() % frame.size());
          stream.insert(stream.end(), frame.begin(), frame.end());
          if (clean) clean_packets.push_back(packet);
        }
        const std::size_t garbage = random() % 8;
        for (std::size_t i = 0; i < garbage; ++i) {
          std::uint8_t byte = static_cast<std::uint8_t>(random());
          if (clean && byte == format->header[0]) byte = 0x00;
          stream.push_back(byte);
        }
      }

      StreamDecoder one_shot(*format);
      one_shot.feed(stream);
      const auto expected = drain(one_shot);

      StreamDecoder chunked(*format);
      std::vector<std::size_t> sizes;
      for (int i = 0; i < 7; ++i) sizes.push_back(1 + random() % 17);
      const auto events = decode_chunked(chunked, stream, sizes);
      expect_same_events(events, expected, "trial " + std::to_string(trial));

      std::size_t frame_bytes = 0;
      for (const auto& event : events) {
        if (event.kind == Kind::Frame) frame_bytes += kMinFrameSize + event.packet.params.size();
      }
      EXPECT_EQ(frame_bytes + chunked.discarded_bytes() + chunked.buffered(), stream.size()) << "trial " << trial;
      EXPECT_LE(chunked.buffered(), StreamDecoder::kMaxFrameSize);

      if (clean) {
        ASSERT_EQ(events.size(), clean_packets.size()) << "trial " << trial;
        for (std::size_t i = 0; i < events.size(); ++i) {
          EXPECT_EQ(events[i].kind, Kind::Frame);
          EXPECT_EQ(events[i].packet, clean_packets[i]);
        }
      }
    }
  }
}

}  // namespace
}  // namespace sms::protocol
