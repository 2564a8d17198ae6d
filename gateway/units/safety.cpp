// The safety supervisor and its thread: construction (each bus's watchdog and stop targets, the
// state restored), start and shutdown, facts and motion stops, and its face (safety.h). The rules
// are in safety_*.cpp, one concern each.
#include "gateway/units/safety_impl.h"

#include <algorithm>
#include <filesystem>
#include <future>

#include <spdlog/spdlog.h>
#include <boost/asio/post.hpp>

#include "gateway/service/modbus_request.h"
#include "gateway/service/request_handler.h"

namespace sms::gateway {

std::string_view to_string(WatchdogState state) {
  switch (state) {
    case WatchdogState::Off: return "off";
    case WatchdogState::Armed: return "armed";
    case WatchdogState::Running: return "running";
    case WatchdogState::Tripped: return "tripped";
  }
  return "?";
}

std::string_view to_string(StopCause cause) {
  switch (cause) {
    case StopCause::None: return "none";
    case StopCause::Watchdog: return "watchdog";
    case StopCause::EStop: return "e-stop";
    case StopCause::Start: return "on_start";
    case StopCause::Shutdown: return "on_stop";
    case StopCause::Commissioning: return "commissioning";
  }
  return "?";
}

std::optional<MotionEpoch> admit_or_refuse(SafetySupervisor& safety, MotionRefusalLog& log, std::size_t bus,
                                           std::string_view what, std::uint8_t function, const Reply& reply) {
  auto admitted = safety.admit_motion(bus);
  if (admitted) return *admitted;
  log.refused(what, function, admitted.error());
  reply.send(exception_response(function, ModbusException::ServerDeviceFailure));  // 0x04: motion blocked
  return std::nullopt;
}

void MotionRefusalLog::refused(std::string_view who, std::uint8_t function, std::string_view why) {
  log_.warn(fmt::format("safety: {} FC{:02X}: motion write refused (0x04): {}", who, function, why));
}

SafetySupervisor::Impl::Impl(const config::Config& config, std::vector<BusEngine*> engines,
                             std::vector<std::shared_ptr<MotionGate>> gates)
    : timer_(io_) {
  if (engines.size() != config.buses.size() || gates.size() != config.buses.size()) {
    throw std::invalid_argument("safety: one engine and one motion gate per bus");
  }
  for (std::size_t i = 0; i < config.buses.size(); ++i) {
    const config::BusConfig& bus_config = config.buses[i];
    auto bus = std::make_unique<BusSafety>();
    bus->index = i;
    bus->name = bus_config.name;
    bus->engine = engines[i];
    bus->gate = gates[i];
    bus->packet = bus_config.protocol != protocol::BusProtocol::ModbusRtu;
    bus->sync_read = bus_config.protocol == protocol::BusProtocol::Feetech;
    bus->watchdog = bus_config.watchdog;
    bus->on_start = bus_config.on_start;
    bus->on_stop = bus_config.on_stop;
    bus->state = bus_config.watchdog ? WatchdogState::Armed : WatchdogState::Off;
    std::vector<const config::ServoConfig*> servos;
    for (const auto& servo : config.servos) {
      if (servo.bus_index == i && !servo.passthrough() && !servo.view_of) servos.push_back(&servo);
    }
    std::sort(servos.begin(), servos.end(), [](const auto* a, const auto* b) { return a->unit_id < b->unit_id; });
    for (const config::ServoConfig* servo : servos) {
      const auto& spec = modbus_map::motion_spec(*servo->table);
      bus->targets.push_back(StopTarget{servo->unit_id, servo->servo_id, &spec, config::effective_byte_order(*servo),
                                        config::effective_safe_stop(*servo), modbus_map::stop_context_reads(spec),
                                        servo->response_level, config::effective_stop_deceleration(config, *servo)});
    }
    buses_.push_back(std::move(bus));
  }
  const std::string dir = config::effective_state_dir(config);
  if (!dir.empty()) {
    if (const std::string problem = check_state_dir(dir); !problem.empty()) throw std::runtime_error(problem);
    state_path_ = (std::filesystem::path(dir) / "safety.state").string();
    restore();
    // From now on every change of an engine's owed stops is written (on the safety thread).
    for (const auto& bus : buses_) bus->engine->on_owed_stops_changed([this] { request_persist(); });
  }
}

SafetySupervisor::Impl::~Impl() {
  // The engines may outlive the supervisor: none may call into it once it is gone.
  if (!state_path_.empty()) {
    for (const auto& bus : buses_) bus->engine->on_owed_stops_changed(nullptr);
  }
  stop_thread();
}

void SafetySupervisor::Impl::start() {
  thread_ = std::thread([this] { io_.run(); });
  if (state_path_.empty()) {
    spdlog::warn(
        "safety: no state_dir: a restart forgets a latched e-stop and tripped watchdogs (set state_dir, "
        "config/README.md)");
  }
  for (const auto& bus : buses_) {
    if (bus->watchdog) {
      spdlog::info("safety: bus {}: watchdog armed: {} ms, fed by {}, then {}", bus->name,
                   bus->watchdog->timeout.count(), config::to_string(bus->watchdog->feed),
                   bus->watchdog->action ? std::string(modbus_map::to_string(*bus->watchdog->action))
                                         : std::string("each servo's safe_stop"));
    }
    // A latch or a trip restored from before the restart: whatever the servos did meanwhile,
    // they are stopped again (the stop the gateway owed them may never have reached them).
    const bool tripped = bus->state.load() == WatchdogState::Tripped;
    if (estop_latched_.load() || tripped) {
      const StopCause cause = tripped ? StopCause::Watchdog : StopCause::EStop;
      const auto action = tripped && bus->watchdog ? bus->watchdog->action : std::nullopt;
      asio::post(io_, [this, index = bus->index, cause, action] {
        run_stop(index, cause, action, Clock::now(), "restored at start", nullptr);
      });
      continue;
    }
    if (bus->on_start == config::StartAction::Keep) continue;
    const StopAction action = bus->on_start == config::StartAction::Hold ? StopAction::Hold : StopAction::TorqueOff;
    asio::post(io_, [this, index = bus->index, action] {
      run_stop(index, StopCause::Start, action, Clock::now(), "on_start", nullptr);
    });
  }
}

void SafetySupervisor::Impl::stop_for_shutdown(std::chrono::milliseconds bound) {
  if (shutdown_done_.exchange(true) || !thread_.joinable()) return;
  {
    std::lock_guard lock(state_mutex_);
    shutting_down_ = true;
    apply_gates_locked();
  }
  auto remaining = std::make_shared<std::atomic<std::size_t>>(buses_.size());
  auto finished = std::make_shared<std::promise<void>>();
  auto all_done = finished->get_future();
  if (buses_.empty()) finished->set_value();
  for (const auto& bus : buses_) {
    if (bus->lent.load()) {
      // Its line is someone else's now; its servos had their safe stop when it was stopped.
      spdlog::info("safety: bus {}: stopped for commissioning: no on_stop (its servos were stopped then)", bus->name);
      if (remaining->fetch_sub(1) == 1) finished->set_value();
      continue;
    }
    asio::post(io_, [this, index = bus->index, action = bus->on_stop, remaining, finished] {
      run_stop(index, StopCause::Shutdown, action, Clock::now(), "the gateway is stopping",
               [remaining, finished](bool) {
                 if (remaining->fetch_sub(1) == 1) finished->set_value();
               });
    });
  }
  if (all_done.wait_for(bound) != std::future_status::ready) {
    spdlog::error("safety: on_stop did not finish within {} ms; stopping the buses anyway", bound.count());
  }
  stop_thread();
  // What on_stop could not deliver is owed at the next start: written now, the safety thread
  // that writes it otherwise has ended.
  persist();
}

SafetyFacts SafetySupervisor::Impl::facts() const {
  SafetyFacts facts;
  facts.estops = estops_.load();
  const auto now = Clock::now();
  // One snapshot of the latch, the states and the gates (they change together, under this lock).
  std::lock_guard lock(state_mutex_);
  facts.estop_latched = estop_latched_.load();
  for (const auto& bus : buses_) {
    BusSafetyFacts f;
    f.state = bus->state.load();
    if (const auto last = bus->last_feed.load(); last != kNever) {
      f.since_feed = std::chrono::duration_cast<std::chrono::milliseconds>(now - from_ticks(last));
    }
    if (const auto trip = bus->last_trip.load(); trip != kNever) {
      f.since_trip = std::chrono::duration_cast<std::chrono::milliseconds>(now - from_ticks(trip));
    }
    f.timeout = bus->watchdog ? bus->watchdog->timeout : std::chrono::milliseconds{0};
    f.trips = bus->trips.load();
    f.stops = bus->stops.load();
    f.failed_stops = bus->failed_stops.load();
    f.owed_stops = bus->engine->owed_stop_count();
    f.last_cause = bus->last_cause.load();
    if (const auto us = bus->last_latency_us.load(); us >= 0) f.last_stop_latency = std::chrono::microseconds{us};
    f.motion_blocked = bus->gate->blocked();
    f.lent = bus->lent.load();
    facts.buses.push_back(f);
  }
  if (not_persisted_.load()) {
    std::lock_guard problem_lock(problem_mutex_);
    facts.state_not_persisted = true;
    facts.state_problem = persist_problem_;
  }
  return facts;
}

MotionStops SafetySupervisor::Impl::motion_stops(std::size_t index) const {
  const BusSafety& bus = *buses_.at(index);
  MotionStops stops;
  // The epoch before `blocked`: a block sets `blocked`, then grows the epoch, so when `blocked`
  // reads false, a block under way as the epoch was read has grown it past that by now.
  stops.epoch = bus.gate->epoch();
  stops.blocked = bus.gate->blocked();
  stops.estop_latched = estop_latched_.load();
  stops.tripped = bus.state.load() == WatchdogState::Tripped;
  stops.lent = bus.lent.load();
  stops.estops = estops_.load();
  stops.trips = bus.trips.load();
  return stops;
}

bool SafetySupervisor::Impl::estop_latched() const { return estop_latched_.load(); }

const std::string& SafetySupervisor::Impl::state_file() const { return state_path_; }

bool SafetySupervisor::Impl::any_tripped() const {
  return std::any_of(buses_.begin(), buses_.end(),
                     [](const auto& bus) { return bus->state.load() == WatchdogState::Tripped; });
}

std::size_t SafetySupervisor::Impl::bus_count() const { return buses_.size(); }

std::optional<std::chrono::milliseconds> SafetySupervisor::Impl::watchdog_timeout(std::size_t index) const {
  const auto& bus = *buses_.at(index);
  if (!bus.watchdog) return std::nullopt;
  return bus.watchdog->timeout;
}

SafetySupervisor::PostFn SafetySupervisor::Impl::safety_post() {
  return [this](std::function<void()> work) { asio::post(io_, std::move(work)); };
}

SafetySupervisor::PostFn SafetySupervisor::Impl::run_here() {
  return [](const std::function<void()>& work) { work(); };
}

void SafetySupervisor::Impl::stop_thread() {
  if (!thread_.joinable()) return;
  asio::post(io_, [this] {
    timer_.cancel();
    retry_timer_.cancel();
  });
  work_.reset();
  io_.stop();
  thread_.join();
}

SafetySupervisor::SafetySupervisor(const config::Config& config, std::vector<BusEngine*> engines,
                                   std::vector<std::shared_ptr<MotionGate>> gates)
    : impl_(std::make_unique<Impl>(config, std::move(engines), std::move(gates))) {}
SafetySupervisor::~SafetySupervisor() = default;

void SafetySupervisor::start() { impl_->start(); }
void SafetySupervisor::stop_for_shutdown(std::chrono::milliseconds bound) { impl_->stop_for_shutdown(bound); }
void SafetySupervisor::feed_write(std::size_t bus) { impl_->feed_write(bus); }
void SafetySupervisor::feed_heartbeat(std::size_t bus, std::uint16_t value) { impl_->feed_heartbeat(bus, value); }
std::optional<std::uint16_t> SafetySupervisor::heartbeat_value(std::size_t bus) const {
  return impl_->heartbeat_value(bus);
}
Expected<MotionEpoch> SafetySupervisor::admit_motion(std::size_t bus) { return impl_->admit_motion(bus); }
std::optional<std::string> SafetySupervisor::motion_refusal(std::size_t bus, std::optional<std::uint8_t> servo) const {
  return impl_->motion_refusal(bus, servo);
}
void SafetySupervisor::estop(const PostFn& post, std::function<void(bool)> done, std::string_view who) {
  impl_->estop(post, std::move(done), who);
}
void SafetySupervisor::reset_estop(std::string_view who) { impl_->reset_estop(who); }
void SafetySupervisor::lend_bus(std::size_t bus, std::string_view who, std::function<void(bool)> done) {
  impl_->lend_bus(bus, who, std::move(done));
}
void SafetySupervisor::hold_servo(std::size_t bus, std::uint8_t servo_id, std::string_view who,
                                  std::function<void(bool)> done) {
  impl_->hold_servo(bus, servo_id, who, std::move(done));
}
void SafetySupervisor::return_bus(std::size_t bus, std::string_view who) { impl_->return_bus(bus, who); }
void SafetySupervisor::rearm_watchdogs(std::string_view who) { impl_->rearm_watchdogs(who); }
SafetyFacts SafetySupervisor::facts() const { return impl_->facts(); }
MotionStops SafetySupervisor::motion_stops(std::size_t bus) const { return impl_->motion_stops(bus); }
bool SafetySupervisor::estop_latched() const { return impl_->estop_latched(); }
const std::string& SafetySupervisor::state_file() const { return impl_->state_file(); }
bool SafetySupervisor::any_tripped() const { return impl_->any_tripped(); }
std::size_t SafetySupervisor::bus_count() const { return impl_->bus_count(); }
std::optional<std::chrono::milliseconds> SafetySupervisor::watchdog_timeout(std::size_t bus) const {
  return impl_->watchdog_timeout(bus);
}

}  // namespace sms::gateway
