#include "protocol/packet.h"

#include <gtest/gtest.h>

#include <stdexcept>

namespace sms::protocol {
namespace {

TEST(PacketChecksum, FeetechInvertsTheSum) {
  // PING id 1: ~(01 + 02 + 01) = ~04 = FB (docs/PROTOCOL.md §1.1).
  EXPECT_EQ(checksum(kFeetechFormat, Bytes{0x01, 0x02, 0x01}), 0xFB);
  // The sum wraps before inverting: FE + 02 + 05 = 0x105 -> ~05 = FA.
  EXPECT_EQ(checksum(kFeetechFormat, Bytes{0xFE, 0x02, 0x05}), 0xFA);
}

TEST(PacketChecksum, D55dKeepsThePlainSum) {
  // docs/PROTOCOL.md §1.2: FE + 04 + 03 + 03 + 01 = 0x109 -> 09.
  EXPECT_EQ(checksum(kD55dFormat, Bytes{0xFE, 0x04, 0x03, 0x03, 0x01}), 0x09);
  EXPECT_EQ(checksum(kD55dFormat, Bytes{}), 0x00);
}

TEST(PacketEncode, FramesFeetechWorkedExamples) {
  EXPECT_EQ(encode(kFeetechFormat, Packet{0x01, 0x01, {}}), (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB}));
  EXPECT_EQ(encode(kFeetechFormat, Packet{0x01, 0x02, {0x38, 0x02}}),
            (Bytes{0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE}));
  EXPECT_EQ(encode(kFeetechFormat, Packet{0x01, 0x03, {0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03}}),
            (Bytes{0xFF, 0xFF, 0x01, 0x09, 0x03, 0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03, 0xD5}));
  // Status replies: CODE is the ERROR byte.
  EXPECT_EQ(encode(kFeetechFormat, Packet{0x01, 0x00, {0x18, 0x05}}),
            (Bytes{0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD}));
}

TEST(PacketEncode, FramesD55dWorkedExample) {
  EXPECT_EQ(encode(kD55dFormat, Packet{0xFE, 0x03, {0x03, 0x01}}),
            (Bytes{0xD5, 0x5D, 0xFE, 0x04, 0x03, 0x03, 0x01, 0x09}));
}

TEST(PacketEncode, AcceptsTheLargestParameterBlockAndRefusesOneMore) {
  const Bytes largest = encode(kFeetechFormat, Packet{0x01, 0x03, Bytes(kMaxParams, 0x00)});
  ASSERT_EQ(largest.size(), kMinFrameSize + kMaxParams);
  EXPECT_EQ(largest[3], 0xFF);  // LEN = 253 + 2
  EXPECT_THROW(encode(kFeetechFormat, Packet{0x01, 0x03, Bytes(kMaxParams + 1, 0x00)}), std::length_error);
}

}  // namespace
}  // namespace sms::protocol
