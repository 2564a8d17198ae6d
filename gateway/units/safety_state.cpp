// What survives a restart (docs/SAFETY.md): the latch, the tripped watchdogs and the owed stops
// in <state_dir>/safety.state, restored at start and written on every change, retried while it
// cannot be.
#include "gateway/units/safety_impl.h"

#include <algorithm>
#include <filesystem>

#include <spdlog/spdlog.h>
#include <boost/asio/post.hpp>

namespace sms::gateway {

// --- the state file --------------------------------------------------------------------------
BusSafety* SafetySupervisor::Impl::bus_named(const std::string& name) const {
  auto found = std::find_if(buses_.begin(), buses_.end(), [&](const auto& b) { return b->name == name; });
  return found == buses_.end() ? nullptr : found->get();
}

void SafetySupervisor::Impl::restore() {
  const auto text = read_state_file(state_path_);
  std::string problem;
  if (!text) {
    problem = text.error();
  } else if (!text->has_value()) {
    return;  // first start
  } else if (auto state = parse_safety_state(**text); !state) {
    problem = state_path_ + " is not a complete safety state: " + state.error();
  } else {
    restore(*state);
  }
  if (!problem.empty()) {
    estop_latched_ = true;
    spdlog::error(
        "safety: {}; the e-stop is LATCHED as a precaution (whether the cell was stopped is unknown): check "
        "the cell, then reset the e-stop (gateway unit coil 1 := 0), which writes a new state file",
        problem);
  }
  std::lock_guard lock(state_mutex_);
  apply_gates_locked();
}

void SafetySupervisor::Impl::restore(const SafetyStateRecord& state) {
  // A name the configuration no longer has is stale, not damage: said, and left alone.
  for (const auto& name : state.tripped_watchdogs) {
    BusSafety* bus = bus_named(name);
    if (bus == nullptr || !bus->watchdog) {
      spdlog::warn("safety: {} names a tripped watchdog on bus `{}`, which has none now: ignored", state_path_, name);
      continue;
    }
    bus->state = WatchdogState::Tripped;
    spdlog::warn(
        "safety: bus {}: its watchdog was tripped before the restart ({}): it stays tripped until a "
        "client re-arms it (gateway unit coil 2 := 0)",
        name, state_path_);
  }
  restore_owed(state);
  if (state.estop_latched) {
    estop_latched_ = true;
    spdlog::warn(
        "safety: the E-STOP was latched before the restart ({}): it stays latched until a client "
        "resets it (gateway unit coil 1 := 0)",
        state_path_);
  }
}

// A write of the whole state from the safety thread, soon (a change of an engine's owed stops,
// on whatever thread made it). Changes close together are written once.
void SafetySupervisor::Impl::request_persist() {
  if (state_path_.empty() || persist_queued_.exchange(true)) return;
  asio::post(io_, [this] {
    persist_queued_ = false;  // before the snapshot: a change after it queues another write
    persist();
  });
}

// Writes the latch, the tripped watchdogs and the owed stops (any thread; serialised). A write
// that fails is said once, shown (facts().state_not_persisted) and retried every second.
void SafetySupervisor::Impl::persist() {
  if (state_path_.empty()) return;
  std::lock_guard file_lock(persist_mutex_);
  SafetyStateRecord state;
  {
    std::lock_guard lock(state_mutex_);
    state.estop_latched = estop_latched_.load();
    for (const auto& bus : buses_) {
      if (bus->state.load() == WatchdogState::Tripped) state.tripped_watchdogs.push_back(bus->name);
    }
  }
  for (const auto& bus : buses_) {
    for (const OwedStop& owed : bus->engine->owed_stops()) {
      state.owed_stops.push_back(OwedStopRecord{bus->name, owed.write.servo_id, owed.why, owed.write.expect_reply});
    }
  }
  const auto written = write_file_atomically(state_path_, render_safety_state(state));
  if (written) {
    if (not_persisted_.exchange(false)) {
      spdlog::warn("safety: the safety state is kept in {} again", state_path_);
    }
    return;
  }
  {
    std::lock_guard problem_lock(problem_mutex_);
    persist_problem_ = written.error();
  }
  if (!not_persisted_.exchange(true)) {
    spdlog::error(
        "safety: SAFETY STATE NOT PERSISTED: {}; a restart now would forget the e-stop latch, tripped "
        "watchdogs and owed stops. Retried every {} s; make {} writable (disk full? read-only? permissions?). "
        "Shown until a save succeeds: gateway unit discrete input 4, sms_gateway_safety_state_not_persisted, "
        "/healthz",
        written.error(), kPersistRetry.count(), std::filesystem::path(state_path_).parent_path().string());
  }
  asio::post(io_, [this] { arm_persist_retry(); });
}

// Safety thread.
void SafetySupervisor::Impl::arm_persist_retry() {
  if (retry_armed_) return;
  retry_armed_ = true;
  retry_timer_.expires_after(kPersistRetry);
  retry_timer_.async_wait([this](const boost::system::error_code& error) {
    retry_armed_ = false;
    if (!error && not_persisted_.load()) persist();
  });
}

}  // namespace sms::gateway
