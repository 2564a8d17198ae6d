#include "gateway/bus/packet_rules.h"

#include <array>
#include <stdexcept>
#include <string>

#include "protocol/d55d.h"
#include "protocol/feetech.h"

namespace sms::gateway {
namespace {

constexpr std::array<PacketRules, 2> kPacketRules{{
    {protocol::BusProtocol::Feetech, &protocol::kFeetechFormat, protocol::feetech::error_bit::kAngle, 0, true, 0,
     &protocol::feetech::instruction_name},
    {protocol::BusProtocol::D55d, &protocol::kD55dFormat,
     protocol::d55d::error_bit::kInstruction | protocol::d55d::error_bit::kChecksum,
     protocol::d55d::error_bit::kChecksum, false, 1, &protocol::d55d::instruction_name},
}};

}  // namespace

const PacketRules& packet_rules(protocol::BusProtocol protocol) {
  for (const auto& rules : kPacketRules) {
    if (rules.protocol == protocol) return rules;
  }
  throw std::invalid_argument("no packet rules for " + std::string(protocol::to_string(protocol)) +
                              " (packet protocols are feetech and d55d)");
}

Verdict judge_reply(const PacketRules& rules, ReplyKind kind, std::uint8_t servo_id, std::size_t count,
                    const protocol::Packet& frame) {
  const auto refusal = [&] {
    return (frame.code & rules.refusal_bits & ~rules.damaged_bits) != 0 ? Verdict::Refused : Verdict::RefusedDamaged;
  };
  if (kind == ReplyKind::Ping && servo_id == protocol::kBroadcastId) {
    // A broadcast PING (the tools' rate scan) is answered by whoever is there; no servo has the
    // broadcast ID, so a frame from it is our own echo.
    const bool answer = frame.id != protocol::kBroadcastId && frame.params.size() <= rules.max_ping_params;
    return answer ? Verdict::Answer : Verdict::NotOurs;
  }
  if (kind == ReplyKind::None || (kind != ReplyKind::SyncRead && frame.id != servo_id)) return Verdict::NotOurs;
  switch (kind) {
    case ReplyKind::None: break;
    case ReplyKind::Ack:
      if ((frame.code & rules.refusal_bits) != 0) return refusal();
      return frame.params.empty() ? Verdict::Answer : Verdict::NotOurs;
    case ReplyKind::Data:
      if (frame.params.size() == count) return Verdict::Answer;
      return (frame.code & rules.refusal_bits) != 0 ? refusal() : Verdict::NotOurs;
    case ReplyKind::Ping: return frame.params.size() <= rules.max_ping_params ? Verdict::Answer : Verdict::NotOurs;
    case ReplyKind::SyncRead: return frame.params.size() == count ? Verdict::Answer : Verdict::NotOurs;
  }
  return Verdict::NotOurs;
}

}  // namespace sms::gateway
