#include "gateway/service/access_gate.h"

#include <fmt/format.h>

namespace sms::gateway {

void RefusalCounter::count(config::Role role) {
  by_role_.at(static_cast<std::size_t>(role)).fetch_add(1, std::memory_order_relaxed);
}

std::uint64_t RefusalCounter::of(config::Role role) const {
  return by_role_.at(static_cast<std::size_t>(role)).load(std::memory_order_relaxed);
}

std::uint64_t RefusalCounter::total() const {
  std::uint64_t sum = 0;
  for (const auto& count : by_role_) sum += count.load(std::memory_order_relaxed);
  return sum;
}

std::string GateRefusal::text() const {
  return "refused for role " + std::string(config::to_string(role)) + ": " + reason;
}

Bytes GateRefusal::answer(std::span<const std::uint8_t> pdu) const {
  return exception_response(pdu.empty() ? 0 : pdu[0], exception);
}

AccessGate::AccessGate(const RolePolicy& policy, std::string way, RefusalCounter* counter)
    : policy_(policy), way_(std::move(way)), counter_(counter) {}

std::optional<GateRefusal> AccessGate::check(config::Role role, std::uint8_t unit, std::span<const std::uint8_t> pdu,
                                             std::string_view who) {
  auto refusal = policy_.refusal(role, unit, pdu);
  if (!refusal) return std::nullopt;
  GateRefusal refused{role, refusal->exception, std::move(refusal->reason)};
  if (counter_ != nullptr) counter_->count(role);
  log_.warn(fmt::format("{}{}: unit {} FC{:02X} refused (0x{:02X}) for role {}: {}", way_,
                        who.empty() ? "" : " (" + std::string(who) + ")", unit, pdu.empty() ? 0 : pdu[0],
                        static_cast<std::uint8_t>(refused.exception), config::to_string(role), refused.reason));
  return refused;
}

RoleGate::RoleGate(const RolePolicy& policy, config::Role role, std::string way, RefusalCounter* counter,
                   RequestHandler& next)
    : gate_(policy, std::move(way), counter), role_(role), next_(next) {}

void RoleGate::handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) {
  if (const auto refusal = gate_.check(role_, unit_id, pdu)) {
    reply.send(refusal->answer(pdu));
    return;
  }
  next_.handle(unit_id, pdu, std::move(reply));
}

}  // namespace sms::gateway
