#include "gateway/bus/poll_scheduler.h"

#include <algorithm>
#include <utility>

namespace sms::gateway {

PollScheduler::PollScheduler(std::vector<PollTarget> targets, std::chrono::milliseconds probe_period)
    : targets_(std::move(targets)), states_(targets_.size()), probe_period_(probe_period) {}

std::optional<std::size_t> PollScheduler::index_of(std::uint8_t servo_id) const {
  const auto found = std::find_if(targets_.begin(), targets_.end(),
                                  [servo_id](const PollTarget& target) { return target.servo_id == servo_id; });
  if (found == targets_.end()) return std::nullopt;
  return static_cast<std::size_t>(found - targets_.begin());
}

PollCyclePlan PollScheduler::plan_cycle(SteadyClock::time_point now, bool polls) const {
  PollCyclePlan plan;
  for (std::size_t i = 0; i < targets_.size(); ++i) {
    const PollTarget& target = targets_[i];
    const State& state = states_[i];
    if (state.presence == Presence::Offline) {
      if (now >= state.next_probe) plan.probes.push_back(target.servo_id);
      continue;
    }
    if (!polls) continue;
    if (!target.sync_read) {
      plan.reads.push_back(target.servo_id);
      continue;
    }
    auto group = std::find_if(plan.sync_reads.begin(), plan.sync_reads.end(),
                              [&](const PollCyclePlan::SyncRead& sync) { return sync.block == target.block; });
    if (group == plan.sync_reads.end()) {
      plan.sync_reads.push_back({target.block, {}});
      group = plan.sync_reads.end() - 1;
    }
    group->ids.push_back(target.servo_id);
  }
  // A SYNC READ for one servo costs more bytes than a READ and buys nothing.
  for (auto it = plan.sync_reads.begin(); it != plan.sync_reads.end();) {
    if (it->ids.size() == 1) {
      plan.reads.push_back(it->ids.front());
      it = plan.sync_reads.erase(it);
    } else {
      ++it;
    }
  }
  return plan;
}

PresenceChange PollScheduler::answered(std::uint8_t servo_id) {
  const auto index = index_of(servo_id);
  if (!index) return PresenceChange::None;
  State& state = states_[*index];
  const bool was_offline = state.presence == Presence::Offline;
  state.presence = Presence::Online;
  return was_offline ? PresenceChange::CameOnline : PresenceChange::None;
}

PresenceChange PollScheduler::silent(std::uint8_t servo_id, SteadyClock::time_point now,
                                     std::optional<std::chrono::milliseconds> next_probe_in) {
  const auto index = index_of(servo_id);
  if (!index) return PresenceChange::None;
  State& state = states_[*index];
  const bool was_offline = state.presence == Presence::Offline;
  state.presence = Presence::Offline;
  state.next_probe = now + std::min(next_probe_in.value_or(probe_period_), probe_period_);
  return was_offline ? PresenceChange::None : PresenceChange::WentOffline;
}

void PollScheduler::forget_all() {
  for (auto& state : states_) state = State{};
}

Presence PollScheduler::presence(std::uint8_t servo_id) const {
  const auto index = index_of(servo_id);
  return index ? states_[*index].presence : Presence::Unknown;
}

const PollTarget* PollScheduler::target(std::uint8_t servo_id) const {
  const auto index = index_of(servo_id);
  return index ? &targets_[*index] : nullptr;
}

std::optional<SteadyClock::time_point> PollScheduler::next_probe_due() const {
  std::optional<SteadyClock::time_point> earliest;
  for (const auto& state : states_) {
    if (state.presence != Presence::Offline) continue;
    if (!earliest || state.next_probe < *earliest) earliest = state.next_probe;
  }
  return earliest;
}

}  // namespace sms::gateway
