// The watchdogs: fed by writes or heartbeat changes, counted on the safety thread, tripped (the
// bus's motion blocked and its servos stopped) when a bus's timeout passes without a feed, and
// re-armed by a client.
#include "gateway/units/safety_impl.h"

#include <spdlog/spdlog.h>
#include <boost/asio/post.hpp>

namespace sms::gateway {

void SafetySupervisor::Impl::feed_write(std::size_t index) {
  BusSafety& bus = *buses_.at(index);
  if (!bus.watchdog || bus.watchdog->feed != config::WatchdogFeed::AnyWrite) return;
  feed(bus);
}

void SafetySupervisor::Impl::feed_heartbeat(std::size_t index, std::uint16_t value) {
  BusSafety& bus = *buses_.at(index);
  const std::uint32_t previous = bus.heartbeat.exchange(value);
  if (!bus.watchdog) return;
  // A frozen PLC repeats its last value: only a change counts. Any write counts under any_write.
  if (bus.watchdog->feed == config::WatchdogFeed::AnyWrite || previous != value) feed(bus);
}

std::optional<std::uint16_t> SafetySupervisor::Impl::heartbeat_value(std::size_t index) const {
  const std::uint32_t value = buses_.at(index)->heartbeat.load();
  if (value == kNoHeartbeat) return std::nullopt;
  return static_cast<std::uint16_t>(value);
}

void SafetySupervisor::Impl::rearm_watchdogs(std::string_view who) {
  std::vector<std::string> rearmed;
  {
    std::lock_guard lock(state_mutex_);
    for (const auto& bus : buses_) {
      WatchdogState tripped = WatchdogState::Tripped;
      if (bus->state.compare_exchange_strong(tripped, WatchdogState::Armed)) rearmed.push_back(bus->name);
    }
    apply_gates_locked();
  }
  if (rearmed.empty()) return;
  persist();
  for (const auto& name : rearmed) {
    spdlog::info("safety: bus {}: watchdog re-armed by {}; nothing moved{}", name, who, owed_text());
  }
}

// --- watchdogs -------------------------------------------------------------------------------
void SafetySupervisor::Impl::feed(BusSafety& bus) {
  bus.last_feed.store(ticks(Clock::now()));
  WatchdogState armed = WatchdogState::Armed;
  if (bus.state.compare_exchange_strong(armed, WatchdogState::Running)) reschedule();
}

void SafetySupervisor::Impl::reschedule() {
  asio::post(io_, [this] { check_watchdogs(); });
}

// Safety thread: trips what is overdue, then sleeps until the next deadline. Feeds only move
// deadlines later, so waking at the earliest one known is enough.
void SafetySupervisor::Impl::check_watchdogs() {
  const auto now = Clock::now();
  std::optional<Clock::time_point> next;
  for (const auto& bus : buses_) {
    if (bus->state.load() != WatchdogState::Running) continue;
    const auto last = from_ticks(bus->last_feed.load());
    const auto deadline = last + bus->watchdog->timeout;
    if (now < deadline) {
      if (!next || deadline < *next) next = deadline;
      continue;
    }
    {
      std::lock_guard lock(state_mutex_);
      WatchdogState running = WatchdogState::Running;
      if (!bus->state.compare_exchange_strong(running, WatchdogState::Tripped)) continue;
      apply_gates_locked();
    }
    bus->last_trip.store(ticks(now));
    bus->trips.fetch_add(1);
    const auto silent = std::chrono::duration_cast<std::chrono::milliseconds>(now - last);
    spdlog::warn(
        "safety: bus {}: WATCHDOG TRIPPED: no {} for {} ms (timeout {} ms); stopping its servos; motion "
        "writes are refused until a client re-arms it (gateway unit coil 2 := 0)",
        bus->name,
        bus->watchdog->feed == config::WatchdogFeed::AnyWrite
            ? std::string("write")
            : "change of heartbeat register " + std::to_string(config::kHeartbeatRegisterBase + bus->index),
        silent.count(), bus->watchdog->timeout.count());
    // The stop first, then the file: a trip has no answer to wait for, and the stop must not.
    run_stop(bus->index, StopCause::Watchdog, bus->watchdog->action, last, "watchdog", nullptr);
    persist();
  }
  if (next) {
    timer_.expires_at(*next);
    timer_.async_wait([this](const boost::system::error_code& error) {
      if (!error) check_watchdogs();
    });
  }
}

}  // namespace sms::gateway
