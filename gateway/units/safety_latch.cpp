// The e-stop latch and lent buses, and the one rule that computes every bus's motion gate from
// the whole state; the admission of a motion write.
#include "gateway/units/safety_impl.h"

#include <stdexcept>

#include <spdlog/spdlog.h>
#include <boost/asio/post.hpp>

namespace sms::gateway {

std::optional<std::string> SafetySupervisor::Impl::motion_refusal(std::size_t index,
                                                                  std::optional<std::uint8_t> servo) const {
  const BusSafety& bus = *buses_.at(index);
  if (estop_latched_.load()) {
    return "bus " + bus.name +
           ": the e-stop is latched; motion writes are refused until it is reset (gateway unit coil 1 := 0)";
  }
  if (bus.state.load() == WatchdogState::Tripped) {
    return "bus " + bus.name + ": its watchdog tripped (no feed for " + std::to_string(bus.watchdog->timeout.count()) +
           " ms); motion writes are refused until it is re-armed (gateway unit coil 2 := 0)";
  }
  if (bus.lent.load()) {
    return "bus " + bus.name +
           ": its line is lent to commissioning (stopped from the browser console); motion writes are "
           "refused until the bus is started again there";
  }
  if (bus.gate->blocked()) return "bus " + bus.name + ": motion is blocked while the gateway stops";
  // The bus engine refuses motion to a servo that owes its stop (EngineCore::owed_refusal).
  if (servo && bus.engine->owed_stop_count() > 0) {
    for (const auto& owed : bus.engine->owed_stops()) {
      if (owed.write.servo_id != *servo) continue;
      return "bus " + bus.name + ": servo " + std::to_string(*servo) + " owes a safe stop (" + owed.why +
             ") it has not taken yet; motion writes to it are refused until it has";
    }
  }
  return std::nullopt;
}

Expected<MotionEpoch> SafetySupervisor::Impl::admit_motion(std::size_t index) {
  BusSafety& bus = *buses_.at(index);
  if (auto refused = motion_refusal(index, std::nullopt)) return unexpected(std::move(*refused));
  // A motion command always has a running watchdog behind it, whatever feeds it. The count
  // starts here: the time goes in before the state says Running (the safety thread reads both).
  if (bus.state.load() == WatchdogState::Armed) {
    bus.last_feed.store(ticks(Clock::now()));
    WatchdogState armed = WatchdogState::Armed;
    if (bus.state.compare_exchange_strong(armed, WatchdogState::Running)) reschedule();
  }
  return bus.gate->epoch();
}

void SafetySupervisor::Impl::estop(const PostFn& post, std::function<void(bool)> done, std::string_view who) {
  bool already = false;
  {
    std::lock_guard lock(state_mutex_);
    already = estop_latched_.exchange(true);
    apply_gates_locked();
  }
  if (!already) {
    estops_.fetch_add(1);
    spdlog::warn(
        "safety: E-STOP latched by {} (gateway unit coil 1): every bus stops; motion writes are refused "
        "until coil 1 is written 0",
        who);
  }
  const auto requested = Clock::now();
  auto remaining = std::make_shared<std::atomic<std::size_t>>(buses_.size());
  auto all_ok = std::make_shared<std::atomic<bool>>(true);
  // The latch is on disk before the answer: the answer waits for the stop frames, and the file
  // is written while they go out.
  auto finish = [this, post, done = std::move(done), all_ok]() {
    persist();
    post([done, ok = all_ok->load()] { done(ok); });
  };
  if (buses_.empty()) {
    finish();
    return;
  }
  for (const auto& bus : buses_) {
    asio::post(io_, [this, index = bus->index, requested, remaining, all_ok, finish] {
      run_stop(index, StopCause::EStop, std::nullopt, requested, "e-stop", [remaining, all_ok, finish](bool ok) {
        if (!ok) all_ok->store(false);
        if (remaining->fetch_sub(1) == 1) finish();
      });
    });
  }
}

void SafetySupervisor::Impl::reset_estop(std::string_view who) {
  {
    std::lock_guard lock(state_mutex_);
    if (!estop_latched_.exchange(false)) return;
    apply_gates_locked();
  }
  persist();
  spdlog::warn("safety: e-stop reset by {}; nothing moved, motion writes are accepted again{}", who, owed_text());
}

void SafetySupervisor::Impl::lend_bus(std::size_t index, std::string_view who, std::function<void(bool)> done) {
  BusSafety& bus = *buses_.at(index);
  {
    std::lock_guard lock(state_mutex_);
    bus.lent.store(true);
    apply_gates_locked();
  }
  spdlog::warn(
      "safety: bus {}: stopped by {} to lend its line to commissioning: its servos get their safe stop; "
      "motion writes are refused until it is started again",
      bus.name, who);
  asio::post(io_, [this, index, done = std::move(done)] {
    run_stop(index, StopCause::Commissioning, std::nullopt, Clock::now(), "commissioning", done);
  });
}

void SafetySupervisor::Impl::hold_servo(std::size_t index, std::uint8_t servo_id, std::string_view who,
                                        std::function<void(bool)> done) {
  if (index >= buses_.size()) {  // said on the caller's thread, not lost on the safety thread
    throw std::out_of_range("hold_servo: no bus " + std::to_string(index));
  }
  asio::post(io_,
             [this, index, servo_id, reason = "hold of servo " + std::to_string(servo_id) + " for " + std::string(who),
              done = std::move(done)] {
               run_stop(index, StopCause::None, StopAction::Hold, Clock::now(), reason, done, servo_id);
             });
}

void SafetySupervisor::Impl::return_bus(std::size_t index, std::string_view who) {
  BusSafety& bus = *buses_.at(index);
  {
    std::lock_guard lock(state_mutex_);
    if (!bus.lent.exchange(false)) return;
    apply_gates_locked();
  }
  spdlog::warn("safety: bus {}: started again by {}; nothing moved{}", bus.name, who, owed_text());
}

// The one rule for every gate, from the whole state; call with state_mutex_ held.
void SafetySupervisor::Impl::apply_gates_locked() {
  for (const auto& bus : buses_) {
    const bool blocked =
        shutting_down_ || estop_latched_.load() || bus->lent.load() || bus->state.load() == WatchdogState::Tripped;
    if (blocked != bus->gate->blocked()) bus->gate->set_blocked(blocked);
  }
}

}  // namespace sms::gateway
