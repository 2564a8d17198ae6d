#include "gateway/units/safety.h"

#include <algorithm>
#include <condition_variable>
#include <filesystem>
#include <future>
#include <map>
#include <mutex>
#include <thread>

#include <spdlog/spdlog.h>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/bus/bus_join.h"
#include "gateway/bus/write_batch.h"
#include "gateway/service/modbus_request.h"
#include "gateway/service/request_handler.h"
#include "gateway/units/state_file.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"

namespace sms::gateway {
namespace {

namespace asio = boost::asio;
using modbus_map::StopAction;
using Clock = std::chrono::steady_clock;

constexpr std::int64_t kNever = std::numeric_limits<std::int64_t>::min();
constexpr std::uint32_t kNoHeartbeat = 0x10000;  // above every register value

std::int64_t ticks(Clock::time_point when) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(when.time_since_epoch()).count();
}
Clock::time_point from_ticks(std::int64_t value) { return Clock::time_point(std::chrono::nanoseconds(value)); }

// One servo a safe stop covers.
struct StopTarget {
  std::uint8_t unit_id = 0;
  std::uint8_t servo_id = 0;
  const modbus_map::MotionSpec* spec = nullptr;
  modbus_map::ByteOrder order = modbus_map::ByteOrder::LowFirst;
  StopAction action = StopAction::Hold;
  std::vector<modbus_map::BusRange> context;   // what to read before a hold
  std::optional<std::uint8_t> response_level;  // as configured; empty: as read from the servo
};

struct BusSafety {
  std::size_t index = 0;
  std::string name;
  BusEngine* engine = nullptr;
  std::shared_ptr<MotionGate> gate;
  bool packet = true;      // SYNC WRITE exists
  bool sync_read = false;  // SYNC READ exists (feetech)
  std::optional<config::WatchdogConfig> watchdog;
  config::StartAction on_start = config::StartAction::Keep;
  StopAction on_stop = StopAction::Hold;
  std::vector<StopTarget> targets;  // unit order

  std::atomic<WatchdogState> state{WatchdogState::Off};
  std::atomic<std::int64_t> last_feed{kNever};
  std::atomic<std::uint32_t> heartbeat{kNoHeartbeat};
  std::atomic<std::uint64_t> trips{0};
  std::atomic<std::uint64_t> stops{0};
  std::atomic<std::uint64_t> failed_stops{0};
  std::atomic<StopCause> last_cause{StopCause::None};
  std::atomic<std::int64_t> last_latency_us{-1};
  // Its line is lent to the console's commissioning (lend_bus): motion refused until returned.
  // Written under state_mutex_ (it is part of the gate's rule), read without it too.
  std::atomic<bool> lent{false};
};

std::string targets_text(const std::vector<std::string>& parts) {
  std::string text;
  for (const auto& part : parts) {
    if (!text.empty()) text += "; ";
    text += part;
  }
  return text;
}

}  // namespace

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

class SafetySupervisor::Impl {
 public:
  Impl(const config::Config& config, std::vector<BusEngine*> engines, std::vector<std::shared_ptr<MotionGate>> gates)
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
                                          servo->response_level});
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

  ~Impl() {
    // The engines may outlive the supervisor: none may call into it once it is gone.
    if (!state_path_.empty()) {
      for (const auto& bus : buses_) bus->engine->on_owed_stops_changed(nullptr);
    }
    stop_thread();
  }

  void start() {
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

  void stop_for_shutdown(std::chrono::milliseconds bound) {
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

  void feed_write(std::size_t index) {
    BusSafety& bus = *buses_.at(index);
    if (!bus.watchdog || bus.watchdog->feed != config::WatchdogFeed::AnyWrite) return;
    feed(bus);
  }

  void feed_heartbeat(std::size_t index, std::uint16_t value) {
    BusSafety& bus = *buses_.at(index);
    const std::uint32_t previous = bus.heartbeat.exchange(value);
    if (!bus.watchdog) return;
    // A frozen PLC repeats its last value: only a change counts. Any write counts under any_write.
    if (bus.watchdog->feed == config::WatchdogFeed::AnyWrite || previous != value) feed(bus);
  }

  std::optional<std::uint16_t> heartbeat_value(std::size_t index) const {
    const std::uint32_t value = buses_.at(index)->heartbeat.load();
    if (value == kNoHeartbeat) return std::nullopt;
    return static_cast<std::uint16_t>(value);
  }

  Expected<MotionEpoch> admit_motion(std::size_t index) {
    BusSafety& bus = *buses_.at(index);
    if (estop_latched_.load()) {
      return unexpected(
          "bus " + bus.name +
          ": the e-stop is latched; motion writes are refused until it is reset (gateway unit coil 1 := 0)");
    }
    if (bus.state.load() == WatchdogState::Tripped) {
      return unexpected("bus " + bus.name + ": its watchdog tripped (no feed for " +
                        std::to_string(bus.watchdog->timeout.count()) +
                        " ms); motion writes are refused until it is re-armed (gateway unit coil 2 := 0)");
    }
    if (bus.lent.load()) {
      return unexpected("bus " + bus.name +
                        ": its line is lent to commissioning (stopped from the browser console); motion writes are "
                        "refused until the bus is started again there");
    }
    if (bus.gate->blocked()) {
      return unexpected("bus " + bus.name + ": motion is blocked while the gateway stops");
    }
    // A motion command always has a running watchdog behind it, whatever feeds it. The count
    // starts here: the time goes in before the state says Running (the safety thread reads both).
    if (bus.state.load() == WatchdogState::Armed) {
      bus.last_feed.store(ticks(Clock::now()));
      WatchdogState armed = WatchdogState::Armed;
      if (bus.state.compare_exchange_strong(armed, WatchdogState::Running)) reschedule();
    }
    return bus.gate->epoch();
  }

  void estop(const PostFn& post, std::function<void(bool)> done, std::string_view who) {
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

  void lend_bus(std::size_t index, std::string_view who, std::function<void(bool)> done) {
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

  void return_bus(std::size_t index, std::string_view who) {
    BusSafety& bus = *buses_.at(index);
    {
      std::lock_guard lock(state_mutex_);
      if (!bus.lent.exchange(false)) return;
      apply_gates_locked();
    }
    spdlog::warn("safety: bus {}: started again by {}; nothing moved{}", bus.name, who, owed_text());
  }

  void reset_estop(std::string_view who) {
    {
      std::lock_guard lock(state_mutex_);
      if (!estop_latched_.exchange(false)) return;
      apply_gates_locked();
    }
    persist();
    spdlog::warn("safety: e-stop reset by {}; nothing moved, motion writes are accepted again{}", who, owed_text());
  }

  void rearm_watchdogs(std::string_view who) {
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

  SafetyFacts facts() const {
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

  MotionStops motion_stops(std::size_t index) const {
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

  bool estop_latched() const { return estop_latched_.load(); }
  const std::string& state_file() const { return state_path_; }
  bool any_tripped() const {
    return std::any_of(buses_.begin(), buses_.end(),
                       [](const auto& bus) { return bus->state.load() == WatchdogState::Tripped; });
  }
  std::size_t bus_count() const { return buses_.size(); }
  std::optional<std::chrono::milliseconds> watchdog_timeout(std::size_t index) const {
    const auto& bus = *buses_.at(index);
    if (!bus.watchdog) return std::nullopt;
    return bus.watchdog->timeout;
  }

 private:
  // The one rule for every gate, from the whole state; call with state_mutex_ held.
  void apply_gates_locked() {
    for (const auto& bus : buses_) {
      const bool blocked =
          shutting_down_ || estop_latched_.load() || bus->lent.load() || bus->state.load() == WatchdogState::Tripped;
      if (blocked != bus->gate->blocked()) bus->gate->set_blocked(blocked);
    }
  }

  std::string owed_text() const {
    std::size_t owed = 0;
    for (const auto& bus : buses_) owed += bus->engine->owed_stop_count();
    if (owed == 0) return {};
    return "; " + std::to_string(owed) +
           " servo(s) still owe their safe stop and refuse motion until they have taken it";
  }

  // --- the state file --------------------------------------------------------------------------
  BusSafety* bus_named(const std::string& name) const {
    auto found = std::find_if(buses_.begin(), buses_.end(), [&](const auto& b) { return b->name == name; });
    return found == buses_.end() ? nullptr : found->get();
  }

  void restore() {
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

  void restore(const SafetyStateRecord& state) {
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
    for (const auto& owed : state.owed_stops) {
      BusSafety* bus = bus_named(owed.bus);
      const StopTarget* target = nullptr;
      if (bus != nullptr) {
        for (const auto& t : bus->targets) {
          if (t.servo_id == owed.servo) target = &t;
        }
      }
      if (target == nullptr) {
        spdlog::warn(
            "safety: {} says servo {} on bus `{}` was owed its safe stop ({}), but the configuration has no such "
            "servo now: ignored; make sure that servo is stopped",
            state_path_, owed.servo, owed.bus, owed.why);
        continue;
      }
      OwedStop stop = owed_stop_for(*bus, *target, owed.why);
      // The servo's answers are not known before discovery: as they were when the stop was owed.
      if (!target->response_level) stop.write.expect_reply = owed.answers_writes;
      bus->engine->owe_stop(std::move(stop));
      spdlog::warn(
          "safety: bus {}: servo {} was owed its safe stop ({}) before the restart ({}): it is sent before "
          "anything else on the bus, and motion writes to the servo are refused until it has taken it",
          bus->name, owed.servo, owed.why, state_path_);
    }
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
  void request_persist() {
    if (state_path_.empty() || persist_queued_.exchange(true)) return;
    asio::post(io_, [this] {
      persist_queued_ = false;  // before the snapshot: a change after it queues another write
      persist();
    });
  }

  // Writes the latch, the tripped watchdogs and the owed stops (any thread; serialised). A write
  // that fails is said once, shown (facts().state_not_persisted) and retried every second.
  void persist() {
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
  void arm_persist_retry() {
    if (retry_armed_) return;
    retry_armed_ = true;
    retry_timer_.expires_after(kPersistRetry);
    retry_timer_.async_wait([this](const boost::system::error_code& error) {
      retry_armed_ = false;
      if (!error && not_persisted_.load()) persist();
    });
  }

  // --- watchdogs -------------------------------------------------------------------------------
  void feed(BusSafety& bus) {
    bus.last_feed.store(ticks(Clock::now()));
    WatchdogState armed = WatchdogState::Armed;
    if (bus.state.compare_exchange_strong(armed, WatchdogState::Running)) reschedule();
  }

  void reschedule() {
    asio::post(io_, [this] { check_watchdogs(); });
  }

  // Safety thread: trips what is overdue, then sleeps until the next deadline. Feeds only move
  // deadlines later, so waking at the earliest one known is enough.
  void check_watchdogs() {
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

  PostFn safety_post() {
    return [this](std::function<void()> work) { asio::post(io_, std::move(work)); };
  }
  static PostFn run_here() {
    return [](const std::function<void()>& work) { work(); };
  }

  // --- safe stops ------------------------------------------------------------------------------
  // What was read of each target's state, by target index (its context ranges in order).
  using Contexts = std::map<std::size_t, std::vector<BusResult>>;

  // Safety thread. Reads what the holds need, then sends the stop frames; `done(ok)` after the
  // last frame (ok: every servo was reached).
  void run_stop(std::size_t index, StopCause cause, std::optional<StopAction> override, Clock::time_point since,
                const std::string& reason, const std::function<void(bool)>& done) {
    BusSafety& bus = *buses_[index];
    auto contexts = std::make_shared<Contexts>();
    auto write_phase = [this, index, cause, override, since, reason, done, contexts] {
      std::map<std::size_t, std::vector<const BusResult*>> by_target;
      for (const auto& [target, results] : *contexts) {
        for (const auto& result : results) by_target[target].push_back(&result);
      }
      send_stop_frames(index, cause, override, since, reason, done, by_target);
    };
    // Targets whose whole state is one range of a table with SYNC READ are read in one frame per
    // range (a 60-servo arm: one frame instead of 60 READs); the rest, one READ per range. A servo
    // known to be offline is left out of the SYNC READ: the frame would wait a whole response
    // timeout for it; its own READ is answered at once (offline) and it is owed its stop.
    std::map<std::pair<std::uint16_t, std::uint16_t>, std::vector<std::size_t>> by_range;
    std::vector<std::size_t> singly;
    for (std::size_t t = 0; t < bus.targets.size(); ++t) {
      const StopTarget& target = bus.targets[t];
      if (override.value_or(target.action) != StopAction::Hold) continue;
      const auto cached = bus.engine->cache().state(target.servo_id);
      const bool known_offline = bus.engine->discovered() && cached && !cached->online;
      if (bus.sync_read && !known_offline && target.context.size() == 1 &&
          modbus_map::table(target.spec->table).has_sync_read) {
        by_range[{target.context[0].address, target.context[0].count}].push_back(t);
      } else {
        singly.push_back(t);
      }
    }
    std::vector<std::pair<modbus_map::BusRange, std::vector<std::size_t>>> groups;
    for (auto& [range, members] : by_range) {
      if (members.size() == 1) {
        singly.push_back(members[0]);
      } else {
        groups.push_back({modbus_map::BusRange{range.first, range.second}, std::move(members)});
      }
    }
    if (groups.empty()) {
      read_contexts(bus, singly, contexts, write_phase);
      return;
    }
    // Whoever stayed silent in a SYNC READ is read on its own, with the bus's retries, before the
    // frames go out: one missed answer must not turn a hold into a torque off.
    std::vector<SyncReadOp> frames;
    for (const auto& [range, members] : groups) {
      SyncReadOp frame{range.address, range.count, {}};
      for (const std::size_t t : members) frame.ids.push_back(bus.targets[t].servo_id);
      frames.push_back(std::move(frame));
    }
    auto join =
        BusJoin::create(groups.size(), run_here(),
                        [this, index, groups, frames, singly, contexts, write_phase](std::vector<BusResult> results) {
                          std::vector<std::size_t> again = singly;
                          for (std::size_t g = 0; g < groups.size(); ++g) {
                            const auto answers = sync_read_answers(frames[g], results[g]);
                            const auto& members = groups[g].second;
                            for (std::size_t m = 0; m < members.size(); ++m) {
                              if (answers[m]) {
                                (*contexts)[members[m]].push_back(BusResult{BusStatus::Ok, 0, *answers[m], {}});
                              } else {
                                again.push_back(members[m]);
                              }
                            }
                          }
                          read_contexts(*buses_[index], again, contexts, write_phase);
                        });
    for (std::size_t g = 0; g < frames.size(); ++g) submit_safely(bus, frames[g], join->completion(g));
  }

  // Reads every context range of `targets` into `contexts`, then `then()`. The completions run
  // where the last read completes (the bus thread), so the next phase is queued before the engine
  // picks its next job: a poll due meanwhile cannot slip in between.
  void read_contexts(BusSafety& bus, const std::vector<std::size_t>& targets, const std::shared_ptr<Contexts>& contexts,
                     const std::function<void()>& then) {
    std::vector<std::pair<std::size_t, modbus_map::BusRange>> reads;
    for (const std::size_t t : targets) {
      for (const auto& range : bus.targets[t].context) reads.emplace_back(t, range);
    }
    if (reads.empty()) {
      then();
      return;
    }
    auto join = BusJoin::create(reads.size(), run_here(), [reads, contexts, then](std::vector<BusResult> results) {
      for (std::size_t i = 0; i < reads.size(); ++i) (*contexts)[reads[i].first].push_back(std::move(results[i]));
      then();
    });
    for (std::size_t i = 0; i < reads.size(); ++i) {
      const StopTarget& target = bus.targets[reads[i].first];
      submit_safely(bus, ReadOp{target.servo_id, reads[i].second.address, reads[i].second.count}, join->completion(i));
    }
  }

  // The torque off a servo is owed when its stop did not reach it (BusEngine::owe_stop).
  OwedStop owed_stop_for(const BusSafety& bus, const StopTarget& target, std::string_view reason) const {
    const auto write = modbus_map::torque_off_write(*target.spec, target.order);
    const bool answers = answers_writes(target.spec->table, target.response_level, *bus.engine, target.servo_id);
    return OwedStop{WriteOp{target.servo_id, write.address, write.data, false, answers, 0}, std::string(reason)};
  }

  void send_stop_frames(std::size_t index, StopCause cause, std::optional<StopAction> override, Clock::time_point since,
                        const std::string& reason, const std::function<void(bool)>& done,
                        const std::map<std::size_t, std::vector<const BusResult*>>& context) {
    BusSafety& bus = *buses_[index];
    std::vector<std::string> report;
    WriteBatch batch(bus.packet);                         // one SYNC WRITE per write shape on packet buses
    std::vector<std::vector<std::size_t>> frame_targets;  // the targets each frame reaches
    std::vector<std::size_t> unconfirmed;                 // torque off broadcast blind: owed until acknowledged
    const auto add_write = [&](std::size_t t, modbus_map::BusWrite write) {
      const std::size_t frame = batch.add(bus.targets[t].servo_id, write.address, std::move(write.data));
      if (frame_targets.size() <= frame) frame_targets.resize(frame + 1);
      frame_targets[frame].push_back(t);
    };
    for (std::size_t t = 0; t < bus.targets.size(); ++t) {
      const StopTarget& target = bus.targets[t];
      const StopAction action = override.value_or(target.action);
      const std::string who = "servo " + std::to_string(target.servo_id);
      if (action == StopAction::None) {
        report.push_back(who + " none");
        continue;
      }
      if (action == StopAction::TorqueOff) {
        add_write(t, modbus_map::torque_off_write(*target.spec, target.order));
        report.push_back(who + " torque off");
        continue;
      }
      std::vector<protocol::Bytes> data;
      std::string failure;
      const auto found = context.find(t);
      if (found != context.end()) {
        for (const BusResult* result : found->second) {
          if (result->status != BusStatus::Ok) {
            failure = result->detail.empty() ? std::string(gateway::to_string(result->status)) : result->detail;
            break;
          }
          data.push_back(result->data);
        }
      }
      Expected<modbus_map::SafeStopPlan> plan = unexpected(failure);
      if (failure.empty()) {
        plan = modbus_map::plan_safe_stop(*target.spec, action, target.order,
                                          modbus_map::StopContext{target.context, data});
      }
      if (!plan) {
        // Without its state no hold can be computed; an unknown motion must still end.
        spdlog::error("safety: bus {}: {}: cannot hold it ({}); switching its torque off instead", bus.name, who,
                      plan.error());
        add_write(t, modbus_map::torque_off_write(*target.spec, target.order));
        if (bus.packet) unconfirmed.push_back(t);
        report.push_back(who + " torque off (state unreadable)");
        continue;
      }
      for (auto& write : plan->writes) add_write(t, std::move(write));
      report.push_back(who + " " + plan->what);
    }

    std::vector<BusOp> frames = std::move(batch.frames());
    const auto finish = [this, index, cause, since, reason, done, report, frame_targets,
                         unconfirmed](const std::vector<BusResult>& results) {
      BusSafety& b = *buses_[index];
      // Who the stop did not reach: every servo of a frame that failed, and on packet buses those
      // whose torque off went out blind (a broadcast is never acknowledged).
      std::vector<std::size_t> unreached = unconfirmed;
      std::string failure;
      for (std::size_t i = 0; i < results.size(); ++i) {
        if (results[i].status == BusStatus::Ok) continue;
        if (failure.empty())
          failure = results[i].detail.empty() ? std::string(to_string(results[i].status)) : results[i].detail;
        unreached.insert(unreached.end(), frame_targets[i].begin(), frame_targets[i].end());
      }
      std::sort(unreached.begin(), unreached.end());
      unreached.erase(std::unique(unreached.begin(), unreached.end()), unreached.end());
      const bool frames_ok = failure.empty();
      std::string owed;
      for (const std::size_t t : unreached) {
        b.engine->owe_stop(owed_stop_for(b, b.targets[t], reason));
        owed += (owed.empty() ? "" : ", ") + std::to_string(b.targets[t].servo_id);
      }
      const auto latency = std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - since);
      b.last_cause.store(cause);
      if (frames_ok) {
        b.stops.fetch_add(1);
        b.last_latency_us.store(latency.count());
        spdlog::warn("safety: bus {}: safe stop ({}) sent {:.1f} ms after {}: {}{}", b.name, reason,
                     static_cast<double>(latency.count()) / 1000.0,
                     cause == StopCause::Watchdog ? "the last feed" : "the request", targets_text(report),
                     owed.empty() ? std::string()
                                  : "; not confirmed for servo(s) " + owed +
                                        " (state unreadable): their torque off is owed until they acknowledge it");
      } else {
        b.failed_stops.fetch_add(1);
        b.last_latency_us.store(-1);
        spdlog::error(
            "safety: bus {}: safe stop ({}) FAILED: {}; planned: {}; servo(s) {} are owed their stop (torque "
            "off): it is sent the moment they can be reached, before anything else, and motion writes to "
            "them are refused until they have taken it",
            b.name, reason, failure, targets_text(report), owed);
      }
      if (done) done(frames_ok);
    };
    if (frames.empty()) {
      finish({});
      return;
    }
    auto join = BusJoin::create(frames.size(), safety_post(), finish);
    for (std::size_t i = 0; i < frames.size(); ++i) submit_safely(bus, std::move(frames[i]), join->completion(i));
  }

  // A stop must not die on an operation the bus refuses to express (a programming error):
  // it becomes that operation's failure, said in the stop's log line.
  void submit_safely(BusSafety& bus, BusOp op, const Completion& done) {
    try {
      bus.engine->submit(std::move(op), Priority::Safety, done);
    } catch (const std::exception& error) {
      done(BusResult{BusStatus::Dropped, 0, {}, "bus " + bus.name + ": " + error.what()});
    }
  }

  void stop_thread() {
    if (!thread_.joinable()) return;
    asio::post(io_, [this] {
      timer_.cancel();
      retry_timer_.cancel();
    });
    work_.reset();
    io_.stop();
    thread_.join();
  }

  asio::io_context io_;
  asio::executor_work_guard<asio::io_context::executor_type> work_ = asio::make_work_guard(io_);
  asio::steady_timer timer_;
  std::thread thread_;
  std::vector<std::unique_ptr<BusSafety>> buses_;
  // Every change of the latch, a watchdog's tripped state or shutting_down_, and the gates
  // computed from them, happen under this lock (apply_gates_locked).
  mutable std::mutex state_mutex_;
  std::atomic<bool> estop_latched_{false};
  bool shutting_down_ = false;
  std::atomic<std::uint64_t> estops_{0};
  std::atomic<bool> shutdown_done_{false};
  std::string state_path_;  // empty: not kept
  std::mutex persist_mutex_;
  std::atomic<bool> persist_queued_{false};  // request_persist(): a write is posted and has not begun
  std::atomic<bool> not_persisted_{false};   // the last write failed
  mutable std::mutex problem_mutex_;
  std::string persist_problem_;  // guarded by problem_mutex_: why the last write failed
  static constexpr std::chrono::seconds kPersistRetry{1};
  asio::steady_timer retry_timer_{io_};
  bool retry_armed_ = false;  // safety thread only
};

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
void SafetySupervisor::estop(const PostFn& post, std::function<void(bool)> done, std::string_view who) {
  impl_->estop(post, std::move(done), who);
}
void SafetySupervisor::reset_estop(std::string_view who) { impl_->reset_estop(who); }
void SafetySupervisor::lend_bus(std::size_t bus, std::string_view who, std::function<void(bool)> done) {
  impl_->lend_bus(bus, who, std::move(done));
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
