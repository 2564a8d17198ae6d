// The one rule the packet transactor (gateway and integrator tools) judges received frames by
// (gateway/bus/packet_rules.h), case by case for both packet protocols.
#include "gateway/bus/packet_rules.h"

#include <gtest/gtest.h>

#include "protocol/d55d.h"
#include "protocol/feetech.h"

namespace sms::gateway {
namespace {

using protocol::BusProtocol;
using protocol::Packet;

Packet status(std::uint8_t id, std::uint8_t error, protocol::Bytes params = {}) {
  return Packet{id, error, std::move(params)};
}

TEST(PacketRules, EachProtocolHasItsRulesAndModbusHasNone) {
  EXPECT_EQ(packet_rules(BusProtocol::Feetech).format, &protocol::kFeetechFormat);
  EXPECT_EQ(packet_rules(BusProtocol::D55d).format, &protocol::kD55dFormat);
  EXPECT_TRUE(packet_rules(BusProtocol::Feetech).has_sync_read);
  EXPECT_FALSE(packet_rules(BusProtocol::D55d).has_sync_read);
  EXPECT_THROW(packet_rules(BusProtocol::ModbusRtu), std::invalid_argument);
}

TEST(PacketRules, FeetechAngleBitRefusesAWriteButNotAReadWithItsData) {
  const auto& rules = packet_rules(BusProtocol::Feetech);
  const std::uint8_t angle = protocol::feetech::error_bit::kAngle;
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 3, 0, status(3, 0)), Verdict::Answer);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 3, 0, status(3, angle)), Verdict::Refused);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Data, 3, 2, status(3, angle, {1, 2})), Verdict::Answer);  // status, not error
  EXPECT_EQ(judge_reply(rules, ReplyKind::Data, 3, 2, status(3, angle)), Verdict::Refused);         // no data
  EXPECT_EQ(judge_reply(rules, ReplyKind::Data, 3, 2, status(3, 0, {1})), Verdict::NotOurs);        // another shape
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 3, 0, status(4, 0)), Verdict::NotOurs);              // another servo
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, 3, 0, status(3, angle)), Verdict::Answer);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, 3, 0, status(3, 0, {7})), Verdict::NotOurs);
  EXPECT_EQ(judge_reply(rules, ReplyKind::None, 3, 0, status(3, 0)), Verdict::NotOurs);
}

TEST(PacketRules, BroadcastPingIsAnsweredByAnyServoButNotByItsOwnEcho) {
  const auto& rules = packet_rules(BusProtocol::Feetech);
  const std::uint8_t broadcast = protocol::kBroadcastId;
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, broadcast, 0, status(7, 0)), Verdict::Answer);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, broadcast, 0, status(0, 0x20)), Verdict::Answer);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, broadcast, 0, status(7, 0, {1})),
            Verdict::NotOurs);  // not a PING answer
  // FF FF FE 02 01 FE: the request itself, handed back by an echoing adapter.
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, broadcast, 0, status(broadcast, 0x01)), Verdict::NotOurs);
}

TEST(PacketRules, D55dChecksumBitAsksForTheFrameAgainAndInstructionBitRefuses) {
  const auto& rules = packet_rules(BusProtocol::D55d);
  const std::uint8_t checksum = protocol::d55d::error_bit::kChecksum;
  const std::uint8_t instruction = protocol::d55d::error_bit::kInstruction;
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 5, 0, status(5, checksum)), Verdict::RefusedDamaged);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 5, 0, status(5, instruction)), Verdict::Refused);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ack, 5, 0, status(5, checksum | instruction)), Verdict::Refused);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Data, 5, 1, status(5, checksum)), Verdict::RefusedDamaged);
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, 5, 0, status(5, 0, {9})), Verdict::Answer);  // one byte allowed
  EXPECT_EQ(judge_reply(rules, ReplyKind::Ping, 5, 0, status(5, 0, {9, 9})), Verdict::NotOurs);
}

TEST(PacketRules, SyncReadMembersAreJudgedByShapeOnly) {
  const auto& rules = packet_rules(BusProtocol::Feetech);
  EXPECT_EQ(judge_reply(rules, ReplyKind::SyncRead, 0xFE, 2, status(7, 0, {1, 2})), Verdict::Answer);
  EXPECT_EQ(judge_reply(rules, ReplyKind::SyncRead, 0xFE, 2, status(7, 0, {1})), Verdict::NotOurs);
}

}  // namespace
}  // namespace sms::gateway
