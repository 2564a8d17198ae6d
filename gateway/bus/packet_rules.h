#pragma once
// What distinguishes the two packet protocols beyond framing (docs/PROTOCOL.md §1.1, §1.2), and the one rule
// for what a received frame is to the transaction waiting for it. The bus engine and the
// integrator tools both judge frames here, so they agree on refusals, on d55d's "your frame
// arrived damaged" (sent again) and on PING answers. Pure: no I/O. packet_transactor.h has the
// refusal decision.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string_view>

#include "protocol/bus_protocol.h"
#include "protocol/packet.h"

namespace sms::gateway {

struct PacketRules {
  protocol::BusProtocol protocol;
  const protocol::PacketFormat* format;
  std::uint8_t refusal_bits;  // in an answer to WRITE / REG WRITE, or to a READ without its data
  std::uint8_t damaged_bits;  // the refusal bits that say "your frame arrived damaged": sent again
  bool has_sync_read;
  std::size_t max_ping_params;  // d55d's PING answer may carry one byte (docs/PROTOCOL.md §1.2 decision)
  std::optional<std::string_view> (*instruction_name)(std::uint8_t code);
};

// The rules of feetech or d55d; std::invalid_argument for another protocol.
const PacketRules& packet_rules(protocol::BusProtocol protocol);

// What a transaction waits for.
enum class ReplyKind : std::uint8_t {
  None,      // broadcast, or a write the servo does not answer: done once on the wire
  Ack,       // a status packet without parameters (WRITE, REG WRITE)
  Data,      // a status packet with exactly `count` parameters (READ)
  Ping,      // a status packet (PING)
  SyncRead,  // one Data answer from each listed ID (the engine judges which IDs are still owed)
};

enum class Verdict : std::uint8_t {
  NotOurs,  // valid frame, but not the answer: another ID, another shape, a late reply
  Answer,
  Refused,         // the servo answered with a refusal bit
  RefusedDamaged,  // the servo says our frame arrived damaged: send it again
};

// What `frame` is to a transaction waiting for a `kind` answer from `servo_id` (Data: with
// `count` parameters). For SyncRead this judges one member's answer: the caller checks the ID.
// A PING to the broadcast ID is answered by any servo (the first valid answer is the answer).
Verdict judge_reply(const PacketRules& rules, ReplyKind kind, std::uint8_t servo_id, std::size_t count,
                    const protocol::Packet& frame);

}  // namespace sms::gateway
