#include "gateway/bus/engine_core.h"

#include <pthread.h>
#include <sys/prctl.h>

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <limits>
#include <stdexcept>
#include <utility>

#include "gateway/bus/packet_transactor.h"
#include "gateway/bus/rtu_transactor.h"
#include "modbus_map/tables.h"

namespace sms::gateway {

using namespace std::chrono_literals;

namespace {

std::uint32_t saturate_us(SteadyClock::duration duration) {
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(duration).count();
  return static_cast<std::uint32_t>(std::clamp<std::int64_t>(us, 0, std::numeric_limits<std::uint32_t>::max()));
}

// What every bus checks of its settings; the transactor's own limits come from Transactor::check_servo.
template <BusTransactor Transactor>
BusSettings validated(BusSettings settings) {
  const std::string where = "bus " + settings.name + ": ";
  if (settings.serial.baud == 0) throw std::invalid_argument(where + "baud must not be 0");
  if (settings.queue_depth == 0) throw std::invalid_argument(where + "queue depth must be at least 1");
  std::bitset<256> seen;
  for (const auto& servo : settings.servos) {
    const auto& table = modbus_map::table(servo.table);
    const std::string who = where + "servo " + std::to_string(servo.servo_id) + " (" + std::string(table.name) + "): ";
    if (table.protocol != settings.protocol) {
      throw std::invalid_argument(who + "its table is spoken over " + std::string(protocol::to_string(table.protocol)) +
                                  ", not over this " + std::string(protocol::to_string(settings.protocol)) + " bus");
    }
    if (seen.test(servo.servo_id)) throw std::invalid_argument(who + "configured twice on this bus");
    seen.set(servo.servo_id);
    if (const std::string problem = Transactor::check_servo(servo); !problem.empty()) {
      throw std::invalid_argument(who + problem);
    }
  }
  return settings;
}

std::vector<PollCache::ServoEntry> cache_entries(const BusSettings& settings) {
  std::vector<PollCache::ServoEntry> entries;
  for (const auto& servo : settings.servos) entries.push_back({servo.servo_id, servo.poll_block});
  return entries;
}

std::vector<PollTarget> poll_targets(const BusSettings& settings, bool protocol_has_sync_read) {
  std::vector<PollTarget> targets;
  for (const auto& servo : settings.servos) {
    const bool sync = protocol_has_sync_read && modbus_map::table(servo.table).has_sync_read;
    targets.push_back({servo.servo_id, servo.poll_block, sync});
  }
  return targets;
}

}  // namespace

template <BusTransactor Transactor>
EngineCore<Transactor>::EngineCore(BusSettings settings, const TransactorFactory& make_transactor)
    : settings_(validated<Transactor>(std::move(settings))),
      transactor_(make_transactor(settings_, counters_)),
      cache_(cache_entries(settings_), Transactor::kBytesPerAddress),
      scheduler_(poll_targets(settings_, transactor_->has_sync_read()), settings_.probe_period) {}

template <BusTransactor Transactor>
EngineCore<Transactor>::~EngineCore() {
  // A destructor must not throw: a bus that cannot be stopped cleanly is said, not aborted on.
  try {
    stop();
  } catch (const std::exception& error) {
    spdlog::error("bus {}: stopping the engine failed: {}", settings_.name, error.what());
  }
}

// ==== queue and thread ========================================================================

template <BusTransactor Transactor>
void EngineCore<Transactor>::submit(BusOp op, Priority priority, Completion done) {
  Job job;
  job.motion_epoch = motion_epoch_of(op);
  if (const auto* write = std::get_if<WriteOp>(&op)) job.staged_write = write->staged;
  job.action = std::holds_alternative<ActionOp>(op);
  if (const auto* sync_read = std::get_if<SyncReadOp>(&op)) {
    job.sync_read_ids = sync_read->ids;
    job.sync_read_count = sync_read->count;
  }
  if (priority == Priority::Safety && settings_.protocol != protocol::BusProtocol::ModbusRtu) {
    if (const auto* write = std::get_if<WriteOp>(&op)) job.stop_writes.push_back(*write);
    if (const auto* sync = std::get_if<SyncWriteOp>(&op)) {
      for (const auto& entry : sync->entries) job.stop_writes.push_back(WriteOp{entry.id, sync->address, entry.data});
    }
  }
  job.request = transactor_->prepare(std::move(op), attempts());  // const: safe on the caller's thread
  job.done = std::move(done);
  if (queue_.submit(std::move(job), priority)) wake_.notify();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::enqueue_internal(Job job) {
  queue_.push_internal(std::move(job));
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::start() {
  if (thread_.joinable() || !queue_.open()) throw std::logic_error("bus " + settings_.name + ": started twice");
  // Opened here, before the thread runs, so bus_up() is true on return when the port exists.
  try_open();
  thread_ = std::thread([this] { run_thread(); });
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::stop() {
  queue_.close();
  wake_.notify();
  if (!thread_.joinable()) return;
  if (std::this_thread::get_id() == thread_.get_id()) {
    throw std::logic_error("bus " + settings_.name + ": stop() called from the bus thread (inside a completion)");
  }
  thread_.join();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::run_thread() {
  // "bus <name>" in top -H / gdb; Linux limits thread names to 15 characters.
  ::pthread_setname_np(::pthread_self(), ("bus " + settings_.name).substr(0, 15).c_str());
  // Reply deadlines and the RTU frame gap are waited for in ppoll/sleeps of a millisecond or
  // less: Linux's default 50 us timer slack would be line time lost on each.
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
  for (;;) {
    try {
      run_loop();
      break;
    } catch (const std::exception& error) {
      spdlog::critical("bus {}: internal error on the bus thread: {}", settings_.name, error.what());
    }
  }
  shutdown();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::run_loop() {
  for (;;) {
    if (lend_requested_.load()) {
      hand_over_line();
      if (queue_.closing()) return;
      continue;
    }
    if (holding_lent_line_) {  // taken back: open again at once, not after a reopen period
      holding_lent_line_ = false;
      try_open();
      continue;
    }
    if (!transactor_->is_open()) {
      wake_.wait(SteadyClock::now() + settings_.reopen_period);  // or earlier, for stop()
      if (queue_.closing()) return;
      try_open();
      continue;
    }
    deliver_owed_stops();
    if (!transactor_->is_open()) continue;
    start_poll_cycle_if_due();
    std::optional<Job> job = next_job();
    if (job) {
      run(std::move(*job));
      continue;
    }
    if (queue_.closing()) return;
  }
}

// Waits for the next job; nullopt when stopping or when the next poll cycle is due.
template <BusTransactor Transactor>
std::optional<typename EngineCore<Transactor>::Job> EngineCore<Transactor>::next_job() {
  for (;;) {
    if (queue_.closing()) return std::nullopt;
    const auto now = SteadyClock::now();
    // An owed safe stop falls due before anything else is taken. (One that owe_stop() adds after
    // this look wakes the wait below: a notify() before the wait is not lost.)
    std::optional<SteadyClock::time_point> owed_due;
    {
      std::lock_guard lock(owed_mutex_);
      for (const auto& [id, owed] : owed_) {
        if (!owed_due || owed.due < *owed_due) owed_due = owed.due;
      }
    }
    if (owed_due && *owed_due <= now) return std::nullopt;
    if (auto job = queue_.take(now)) return job;
    if (poll_due(now)) return std::nullopt;
    // Asleep until a job is submitted or the next cycle falls due (never a time already past:
    // poll_due() would have said so).
    std::optional<SteadyClock::time_point> wake_at;
    if (settings_.poll && discovered_.load() && !cycle_.running) wake_at = next_cycle_;
    if (owed_due && (!wake_at || *owed_due < *wake_at)) wake_at = owed_due;
    wake_.wait(wake_at);
  }
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::run(Job job) {
  if (auto refusal = motion_refusal(job.motion_epoch)) {
    queue_.complete(job, std::move(*refusal));
    return;
  }
  if (job.motion_epoch != 0) {
    if (auto refusal = owed_refusal(job.request)) {
      queue_.complete(job, std::move(*refusal));
      return;
    }
  }
  const std::uint8_t target = Transactor::target(job.request);
  if ((job.client || job.poll_read) && !Transactor::broadcast(job.request) &&
      scheduler_.presence(target) == Presence::Offline) {
    // A client polling a dead servo must not make the bus pay timeouts; the servo's probe
    // brings it back within one probe period. A poll READ queued before the servo went offline
    // is not sent either.
    counters_.transactions.fetch_add(1, std::memory_order_relaxed);
    const auto state = cache_.state(target);
    const bool late = state && state->offline_reason == OfflineReason::AnswersLate;
    queue_.complete(
        job, BusResult{BusStatus::Timeout,
                       0,
                       {},
                       fmt::format("bus {}: servo {} is offline ({}; probed every {} ms)", settings_.name, target,
                                   late ? "it answers late" : "it stopped answering", settings_.probe_period.count())});
    return;
  }
  note_instructions(job);
  sync_answered_.reset();
  std::map<std::uint8_t, protocol::Bytes> collected;
  if (!job.sync_read_ids.empty()) sync_collect_ = &collected;
  BusResult result = execute(job.request);
  sync_collect_ = nullptr;
  counters_.transactions.fetch_add(1, std::memory_order_relaxed);
  if (!job.sync_read_ids.empty() && result.status == BusStatus::Ok) {
    // sync_read_answers() (bus_operations.h) reads it back: per id, answered or not, its bytes.
    for (const auto id : job.sync_read_ids) {
      const auto found = collected.find(id);
      result.data.push_back(found == collected.end() ? 0 : 1);
      if (found == collected.end()) {
        result.data.insert(result.data.end(), job.sync_read_count, 0);
      } else {
        result.data.insert(result.data.end(), found->second.begin(), found->second.end());
      }
    }
  }
  if (result.status == BusStatus::BusDown) {
    const std::string reason = std::move(result.detail);
    port_lost(reason);  // drops the engine's own work: it is rebuilt when the bus is back
    if (job.client) queue_.complete(job, BusResult{BusStatus::BusDown, 0, {}, "bus " + settings_.name + ": " + reason});
    return;
  }
  if (result.status == BusStatus::Ok) {
    note_written(job.request);
    if (job.staged_write) staged_.set(target);
    if (job.action) staged_.reset();
    if (!job.stop_writes.empty() && staged_.any()) neutralise_staged(job);
  } else {
    spdlog::debug("{}", result.detail);
  }
  queue_.complete(job, std::move(result));
}

template <BusTransactor Transactor>
std::optional<BusResult> EngineCore<Transactor>::motion_refusal(MotionEpoch admitted) const {
  if (admitted == 0 || !settings_.motion_gate || settings_.motion_gate->admits(admitted)) return std::nullopt;
  return BusResult{BusStatus::MotionBlocked,
                   0,
                   {},
                   "bus " + settings_.name +
                       ": motion write dropped: a watchdog trip or the e-stop stopped the bus "
                       "after it was accepted (README \"Safety\")"};
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::shutdown() {
  transactor_->close();
  std::vector<Job> cancelled = queue_.line_down();
  const std::string detail = "bus " + settings_.name + ": the gateway is stopping";
  for (auto& job : cancelled) queue_.complete(job, BusResult{BusStatus::Cancelled, 0, {}, detail});
}

// ==== owed safe stops =============================================================================

template <BusTransactor Transactor>
void EngineCore<Transactor>::owe_stop(OwedStop stop) {
  {
    std::lock_guard lock(owed_mutex_);
    const auto now = SteadyClock::now();
    const std::uint8_t id = stop.write.servo_id;
    auto found = owed_.find(id);
    if (found == owed_.end()) {
      owed_.emplace(id, Owed{std::move(stop), now, now, 0});
      owed_count_.store(owed_.size(), std::memory_order_release);
    } else {
      found->second.stop = std::move(stop);
      found->second.due = now;
    }
  }
  wake_.notify();
  owed_stops_changed();
}

template <BusTransactor Transactor>
std::vector<OwedStop> EngineCore<Transactor>::owed_stops() const {
  std::lock_guard lock(owed_mutex_);
  std::vector<OwedStop> stops;
  for (const auto& [id, owed] : owed_) stops.push_back(owed.stop);
  return stops;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::on_owed_stops_changed(std::function<void()> changed) {
  std::lock_guard lock(owed_listener_mutex_);
  owed_listener_ = std::move(changed);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::owed_stops_changed() {
  std::lock_guard lock(owed_listener_mutex_);
  if (owed_listener_) owed_listener_();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::make_owed_due(std::optional<std::uint8_t> servo_id) {
  std::lock_guard lock(owed_mutex_);
  const auto now = SteadyClock::now();
  for (auto& [id, owed] : owed_) {
    if (!servo_id || id == *servo_id) owed.due = now;
  }
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::deliver_owed_stops() {
  std::vector<std::pair<std::uint8_t, Owed>> due;
  {
    std::lock_guard lock(owed_mutex_);
    const auto now = SteadyClock::now();
    for (const auto& [id, owed] : owed_) {
      if (owed.due <= now) due.emplace_back(id, owed);
    }
  }
  for (const auto& [id, owed] : due) {
    if (!deliver(id, owed)) return;
  }
}

// One attempt (with the bus's retries, or one try while the servo is offline, in place of its
// probe). To an offline servo the stop is first sent blind, without awaiting an answer (a servo
// that hears but whose answers are lost stops all the same), then sent as usual: behind a fence
// read when its answer could be an owed one, so the stop is acknowledged only once the servo
// answers again.
template <BusTransactor Transactor>
bool EngineCore<Transactor>::deliver(std::uint8_t servo_id, const Owed& owed) {
  const bool offline = scheduler_.presence(servo_id) == Presence::Offline;
  const unsigned tries = offline ? 1 : attempts();
  const WriteOp& write = owed.stop.write;
  const Request request = transactor_->prepare(BusOp{write}, tries);
  if (offline) {
    WriteOp blind = write;
    blind.expect_reply = false;
    const BusResult sent = execute(transactor_->prepare(BusOp{blind}, 1));
    counters_.transactions.fetch_add(1, std::memory_order_relaxed);
    if (sent.status == BusStatus::BusDown) {
      port_lost(sent.detail);
      return false;
    }
    if (write.expect_reply) transactor_->owe_answer(request);
  }
  BusResult result = execute(request);
  counters_.transactions.fetch_add(1, std::memory_order_relaxed);
  if (result.status == BusStatus::Ok && !write.expect_reply) {
    // Nothing answers the write itself: a read of what it wrote is the acknowledgement.
    const AddressBlock written{write.address,
                               static_cast<std::uint16_t>(write.data.size() / Transactor::kBytesPerAddress)};
    result = execute(transactor_->read_request(servo_id, written, tries));
    counters_.transactions.fetch_add(1, std::memory_order_relaxed);
    if (result.status == BusStatus::Ok && result.data != write.data) {
      result = BusResult{BusStatus::ServoRefused, 0, {}, "the read-back does not show the stop"};
    }
  }
  if (result.status == BusStatus::BusDown) {
    port_lost(result.detail);
    return false;
  }
  const auto now = SteadyClock::now();
  bool delivered = false;
  {
    std::lock_guard lock(owed_mutex_);
    auto found = owed_.find(servo_id);
    if (found == owed_.end()) return true;
    ++found->second.attempts;
    if (result.status == BusStatus::Ok && found->second.since == owed.since) {
      owed_.erase(found);
      owed_count_.store(owed_.size(), std::memory_order_release);
      delivered = true;
    } else {
      found->second.due = now + settings_.probe_period;
    }
  }
  if (delivered) {
    const auto late = std::chrono::duration_cast<std::chrono::milliseconds>(now - owed.since);
    spdlog::warn("bus {}: servo {} took its owed safe stop ({}: torque off) {} ms after the stop, at attempt {}",
                 settings_.name, servo_id, owed.stop.why, late.count(), owed.attempts + 1);
    owed_stops_changed();
    if (write.expect_reply || offline) servo_answered(servo_id);
  } else {
    spdlog::debug("bus {}: servo {}: owed safe stop not taken yet ({}); next try in {} ms", settings_.name, servo_id,
                  result.detail, settings_.probe_period.count());
  }
  return true;
}

template <BusTransactor Transactor>
std::optional<BusResult> EngineCore<Transactor>::owed_refusal(const Request& request) const {
  if (owed_stop_count() == 0) return std::nullopt;  // every motion write asks: no lock when none is owed
  const std::uint8_t target = Transactor::target(request);
  std::lock_guard lock(owed_mutex_);
  if (owed_.empty()) return std::nullopt;
  const bool broadcast = Transactor::broadcast(request);
  if (!broadcast && owed_.count(target) == 0) return std::nullopt;
  const std::uint8_t owing = broadcast ? owed_.begin()->first : target;
  return BusResult{BusStatus::MotionBlocked,
                   0,
                   {},
                   fmt::format("bus {}: servo {} has not taken its owed safe stop yet ({}); motion writes to it "
                               "are refused until it has",
                               settings_.name, owing, owed_.at(owing).stop.why)};
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::neutralise_staged(const Job& job) {
  for (const WriteOp& write : job.stop_writes) {
    if (!staged_.test(write.servo_id)) continue;
    WriteOp staged = write;
    staged.staged = true;
    const BusResult result = execute(transactor_->prepare(BusOp{staged}, attempts()));
    counters_.transactions.fetch_add(1, std::memory_order_relaxed);
    if (result.status == BusStatus::Ok) {
      spdlog::info(
          "bus {}: servo {} held a staged write: the stop is staged over it (a later ACTION cannot run "
          "the old move)",
          settings_.name, write.servo_id);
    } else {
      spdlog::warn("bus {}: servo {} holds a staged write that the stop could not replace: {}", settings_.name,
                   write.servo_id, result.detail);
    }
  }
}

// ==== port ======================================================================================

template <BusTransactor Transactor>
bool EngineCore<Transactor>::try_open() {
  const auto opened = transactor_->open();
  if (!opened) {
    if (!open_failure_logged_) {
      spdlog::error("bus {}: {}; retrying every {} ms", settings_.name, opened.error(),
                    settings_.reopen_period.count());
      open_failure_logged_ = true;
    } else {
      spdlog::debug("bus {}: still cannot open: {}", settings_.name, opened.error());
    }
    return false;
  }
  open_failure_logged_ = false;
  spdlog::info("bus {}: {} open, {}", settings_.name, settings_.serial.device, transactor_->line_description());
  queue_.line_up();
  make_owed_due(std::nullopt);  // before discovery: run_loop delivers them first
  begin_discovery();
  return true;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::port_lost(const std::string& reason) {
  spdlog::error("bus {}: {} — bus down; reopening every {} ms", settings_.name, reason,
                settings_.reopen_period.count());
  counters_.bus_down_events.fetch_add(1, std::memory_order_relaxed);
  close_line(reason, false);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::close_line(const std::string& why, bool lent) {
  transactor_->close();
  // Before the bus reads down: whoever sees bus_up() false sees the loss logged and counted and
  // every servo offline too.
  cache_.set_all_offline();
  last_instruction_.fill(std::nullopt);
  discovered_.store(false);
  // New work is refused with the lend's reason; after a loss, with "the port is not open".
  std::vector<Job> failed = queue_.line_down(lent ? why : std::string{});
  scheduler_.forget_all();
  cycle_ = Cycle{};
  next_cycle_.reset();
  discovery_ = Discovery{};
  const std::string detail = "bus " + settings_.name + ": " + why;
  for (auto& job : failed) queue_.complete(job, BusResult{BusStatus::BusDown, 0, {}, detail});
}

// ==== lending the line ============================================================================

template <BusTransactor Transactor>
bool EngineCore<Transactor>::lend_line(std::string why, std::chrono::milliseconds bound) {
  if (std::this_thread::get_id() == thread_.get_id()) {
    throw std::logic_error("bus " + settings_.name + ": lend_line() called from the bus thread");
  }
  std::unique_lock lock(lend_mutex_);
  lend_wanted_ = std::move(why);
  lend_requested_.store(true);
  wake_.notify();
  return lend_changed_.wait_for(lock, bound, [this] { return lent_; });
}

template <BusTransactor Transactor>
bool EngineCore<Transactor>::take_back_line() {
  {
    std::lock_guard lock(lend_mutex_);
    if (!lend_wanted_) return false;
    lend_wanted_.reset();
    lend_requested_.store(false);
    lent_ = false;
  }
  wake_.notify();
  return true;
}

template <BusTransactor Transactor>
bool EngineCore<Transactor>::line_lent() const {
  std::lock_guard lock(lend_mutex_);
  return lent_;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::hand_over_line() {
  std::string why;
  {
    std::lock_guard lock(lend_mutex_);
    if (!lend_wanted_) return;  // taken back before the bus thread got here
    why = *lend_wanted_;
  }
  if (!holding_lent_line_) {
    close_line(why, true);
    holding_lent_line_ = true;
    spdlog::warn("bus {}: {}: {} closed; the bus stays down until it is taken back", settings_.name, why,
                 settings_.serial.device);
  }
  {
    // Also for a lend asked for again right after a take-back the bus thread had not acted on:
    // the port is still closed, and the lender waits to hear so.
    std::lock_guard lock(lend_mutex_);
    if (lend_wanted_ && !lent_) {
      lent_ = true;
      lend_changed_.notify_all();
    }
  }
  wake_.wait(std::nullopt);  // take_back_line() and stop() wake it
}

// ==== discovery ===================================================================================

template <BusTransactor Transactor>
const ServoSettings* EngineCore<Transactor>::servo(std::uint8_t servo_id) const {
  for (const auto& each : settings_.servos) {
    if (each.servo_id == servo_id) return &each;
  }
  return nullptr;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::begin_discovery() {
  discovered_.store(false);
  discovery_ = Discovery{};
  for (const auto& each : settings_.servos) {
    DiscoveredServo found;
    found.servo_id = each.servo_id;
    found.table = each.table;
    discovery_.servos.push_back(std::move(found));
  }
  if (!settings_.discover || settings_.servos.empty()) {
    discovered_.store(true);
    next_cycle_ = SteadyClock::now();
    return;
  }
  for (std::size_t index = 0; index < settings_.servos.size(); ++index) {
    Job job;
    job.request = transactor_->ping_request(settings_.servos[index].servo_id, attempts());
    job.done = [this, index](BusResult result) { on_discovery_ping(index, result); };
    ++discovery_.pending;
    enqueue_internal(std::move(job));
  }
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::on_discovery_ping(std::size_t index, const BusResult& result) {
  DiscoveredServo& found = discovery_.servos.at(index);
  if (result.status == BusStatus::Ok) {
    found.online = true;
    // A Modbus PING answered with an exception carries its code there, not a status.
    if (Transactor::kAnswersCarryStatus) found.status = result.servo_error;
    servo_answered(found.servo_id);
    if (identity_layout(found.table) != nullptr) read_identity(found.servo_id, index);
  } else {
    found.detail = result.status == BusStatus::Timeout ? fmt::format("no answer to PING ({} attempts)", attempts())
                                                       : fmt::format("{} answering PING", to_string(result.status));
    servo_silent(found.servo_id, found.detail, false);
  }
  discovery_step_done();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::read_identity(std::uint8_t servo_id, std::optional<std::size_t> discovery_index) {
  const ServoSettings* settings = servo(servo_id);
  const IdentityLayout* layout = settings == nullptr ? nullptr : identity_layout(settings->table);
  if (layout == nullptr) return;
  Job job;
  job.request = transactor_->read_request(servo_id, layout->read, attempts());
  job.done = [this, servo_id, discovery_index, layout, order = settings->byte_order,
              table = settings->table](BusResult result) {
    if (result.status == BusStatus::Ok) {
      const ServoIdentity identity = decode_identity(*layout, result.data, order);
      cache_.set_identity(servo_id, identity);
      cache_.set_response_level(servo_id, decode_response_level(*layout, result.data));
      identity_known_.set(servo_id);
      if (discovery_index) discovery_.servos.at(*discovery_index).identity = identity;
    } else if (result.status == BusStatus::ServoRefused && !identity_refusal_logged_.test(servo_id)) {
      identity_refusal_logged_.set(servo_id);
      spdlog::warn("{} — is servo {} really a {} servo (its identity READ was refused)?", result.detail, servo_id,
                   modbus_map::table(table).name);
    }
    if (discovery_index) discovery_step_done();
  };
  if (discovery_index) ++discovery_.pending;
  enqueue_internal(std::move(job));
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::discovery_step_done() {
  if (discovery_.pending == 0 || --discovery_.pending > 0) return;
  spdlog::info("{}", format_discovery_summary({settings_.name, settings_.serial.device, transactor_->protocol_name(),
                                               settings_.serial.baud, discovery_.servos}));
  discovered_.store(true);
  next_cycle_ = SteadyClock::now();
}

// ==== polling and presence ==========================================================================

template <BusTransactor Transactor>
bool EngineCore<Transactor>::poll_due(SteadyClock::time_point now) const {
  return settings_.poll && discovered_.load() && !cycle_.running && next_cycle_ && now >= *next_cycle_;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::start_poll_cycle_if_due() {
  const auto now = SteadyClock::now();
  if (!poll_due(now)) return;
  const bool polls = now >= next_poll_;
  PollCyclePlan plan = scheduler_.plan_cycle(now, polls);
  skip_probes_of_owed(plan, now);
  if (plan.empty()) {
    schedule_next_cycle(now);  // nobody to poll and no probe due yet
    return;
  }
  cycle_ = Cycle{true, now, 0, polls};
  if (polls) next_poll_ = now + settings_.poll_period;
  next_cycle_.reset();
  for (const auto& sync : plan.sync_reads) {
    Job job;
    job.request = transactor_->sync_read_request(sync.block, sync.ids);
    job.done = [this, ids = sync.ids](const BusResult&) { on_sync_read_finished(ids); };
    ++cycle_.outstanding;
    enqueue_internal(std::move(job));
  }
  for (const auto id : plan.reads) enqueue_poll_read(id, false);
  for (const auto id : plan.probes) enqueue_poll_read(id, true);
}

// An offline servo owed a safe stop is not probed: the stop's delivery, once per probe period,
// is its probe (it brings the servo back when it answers), so a silent servo costs its bus one
// attempt per probe period, not two.
template <BusTransactor Transactor>
void EngineCore<Transactor>::skip_probes_of_owed(PollCyclePlan& plan, SteadyClock::time_point now) {
  if (owed_stop_count() == 0 || plan.probes.empty()) return;
  std::lock_guard lock(owed_mutex_);
  std::erase_if(plan.probes, [&](std::uint8_t id) {
    if (owed_.count(id) == 0) return false;
    scheduler_.silent(id, now);  // its next probe one period on, as if this one had gone unanswered
    return true;
  });
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::enqueue_poll_read(std::uint8_t servo_id, bool probe) {
  const PollTarget* target = scheduler_.target(servo_id);
  if (target == nullptr) return;
  Job job;
  // A probe is one attempt: an offline servo costs at most one timeout per probe period.
  job.request = transactor_->read_request(servo_id, target->block, probe ? 1 : attempts());
  job.poll_read = !probe;
  job.done = [this, servo_id, probe, block = target->block](BusResult result) {
    on_poll_read(servo_id, block, probe, result);
  };
  ++cycle_.outstanding;
  enqueue_internal(std::move(job));
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::on_poll_read(std::uint8_t servo_id, AddressBlock block, bool probe,
                                          const BusResult& result) {
  switch (result.status) {
    case BusStatus::Ok: {
      cache_.store_block(servo_id, result.data, SteadyClock::now());
      if (const auto status = transactor_->status_in_block(block, result.data)) note_status(servo_id, *status);
      poll_refusal_logged_.reset(servo_id);
      servo_answered(servo_id);
      break;
    }
    case BusStatus::ServoRefused:
      servo_answered(servo_id);
      // Once per episode, not every cycle: the configuration will not change by itself.
      if (!poll_refusal_logged_.test(servo_id)) {
        poll_refusal_logged_.set(servo_id);
        spdlog::warn("{} — check the poll block configured for its table (said once until a poll succeeds)",
                     result.detail);
      }
      break;
    case BusStatus::Timeout:
    case BusStatus::Corrupt: servo_silent(servo_id, probe ? "probe unanswered" : result.detail, true); break;
    default: break;
  }
  poll_job_done();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::on_sync_read_finished(const std::vector<std::uint8_t>& ids) {
  // Whoever stayed silent in the SYNC READ is read on its own, with retries, in this cycle:
  // only a failed READ takes a servo offline.
  for (const auto id : ids) {
    if (sync_answered_.test(id)) continue;
    note_timeout(id);
    enqueue_poll_read(id, false);
  }
  poll_job_done();
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::poll_job_done() {
  if (!cycle_.running || --cycle_.outstanding > 0) return;
  const auto now = SteadyClock::now();
  cycle_.running = false;
  if (cycle_.polls) {  // a probe between polls is no poll cycle
    counters_.poll_cycles.fetch_add(1, std::memory_order_relaxed);
    counters_.last_poll_cycle_us.store(saturate_us(now - cycle_.started), std::memory_order_relaxed);
  }
  schedule_next_cycle(now);
}

// A servo went offline outside a cycle (a client's request it did not answer): its probe may be
// due before the cycle already planned.
template <BusTransactor Transactor>
void EngineCore<Transactor>::reschedule_for_probe() {
  if (!cycle_.running && next_cycle_) schedule_next_cycle(SteadyClock::now());
}

// The next cycle: the next poll while anyone is online; a probe due before it goes out on its own
// where the bus is polled more rarely than its servos are probed (poll_period_ms over
// offline_probe_period_ms: a servo offline a moment is back within its probe period, not after an
// hour's poll), or where nobody is online. Elsewhere probes ride on the polls.
template <BusTransactor Transactor>
void EngineCore<Transactor>::schedule_next_cycle(SteadyClock::time_point now) {
  const bool anyone_online = std::any_of(
      scheduler_.targets().begin(), scheduler_.targets().end(),
      [this](const PollTarget& target) { return scheduler_.presence(target.servo_id) != Presence::Offline; });
  std::optional<SteadyClock::time_point> next;
  if (anyone_online) next = next_poll_;
  const auto due = scheduler_.next_probe_due();
  if (due && (!anyone_online || settings_.poll_period > settings_.probe_period)) {
    next = next ? std::min(*next, *due) : *due;
  }
  // Never at once again: a probe that was due and skipped (owed a stop) is due a period on.
  next_cycle_ = next ? std::optional(std::max(*next, now + std::chrono::milliseconds{1})) : std::nullopt;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::servo_answered(std::uint8_t servo_id) {
  // Logged before the cache shows it: whoever sees the servo online finds the line in the log.
  const PresenceChange change = scheduler_.answered(servo_id);
  if (change == PresenceChange::CameOnline) {
    spdlog::info("bus {}: servo {} answers again: online", settings_.name, servo_id);
    make_owed_due(servo_id);
  }
  cache_.set_online(servo_id, true);
  if (change == PresenceChange::CameOnline && !identity_known_.test(servo_id)) {
    read_identity(servo_id, std::nullopt);
  }
}

// A servo offline for answering late may only have been held up (a loaded host stalls the line's
// far end as much as a slow servo does): it is probed again after a poll period (at least 20 ms,
// at most the probe period: a bus polled once an hour must not leave it offline that long), then
// twice as long each time it stays late, up to the probe period.
template <BusTransactor Transactor>
std::chrono::milliseconds EngineCore<Transactor>::first_late_probe() const {
  constexpr std::chrono::milliseconds kShortest{20};
  return std::min(std::max(settings_.poll_period, kShortest), std::max(settings_.probe_period, kShortest));
}

template <BusTransactor Transactor>
std::chrono::milliseconds EngineCore<Transactor>::next_late_probe(std::uint8_t servo_id) {
  auto& in = late_probe_in_[servo_id];
  in = in.count() == 0 ? first_late_probe() : std::min(2 * in, std::max(settings_.probe_period, first_late_probe()));
  return in;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::servo_silent(std::uint8_t servo_id, const std::string& reason, bool log) {
  const auto state = cache_.state(servo_id);
  const bool late = state && !state->online && state->offline_reason == OfflineReason::AnswersLate;
  const PresenceChange change =
      scheduler_.silent(servo_id, SteadyClock::now(), late ? std::optional(next_late_probe(servo_id)) : std::nullopt);
  reschedule_for_probe();
  if (log && change == PresenceChange::WentOffline) {
    spdlog::warn("bus {}: servo {} offline ({}); probing it every {} ms", settings_.name, servo_id, reason,
                 settings_.probe_period.count());
  }
  cache_.set_online(servo_id, false);
}

// A servo that answers late (docs/DECISIONS.md "A servo that answers late"): late answers heard in
// one transaction can be a busy host or one slow reply, and cost only that they were dropped;
// more in a second transaction before the servo answers anything in time shows it answers later than
// response_timeout_ms allows. Retried inline, every request to it would hold the bus for several timeouts at every
// other servo's cost, so it goes offline (probe only) with its own reason until a probe is answered in time.
template <BusTransactor Transactor>
BusResult EngineCore<Transactor>::execute(const Request& request) {
  struck_.reset();
  return transactor_->execute(request, events_);
}

template <BusTransactor Transactor>
bool EngineCore<Transactor>::servo_late(std::uint8_t servo_id, std::chrono::milliseconds after_asked) {
  if (ServoCounters* counters = cache_.counters(servo_id)) {
    counters->late_answers.fetch_add(1, std::memory_order_relaxed);
  }
  constexpr std::uint8_t kLateStrikes = 2;
  if (scheduler_.presence(servo_id) != Presence::Offline) {
    // The late answers one transaction hears count once: a servo held up once (a host that stalled
    // it) owes an answer for each attempt it missed, and they all come together.
    if (struck_.test(servo_id)) return false;
    struck_.set(servo_id);
    if (++late_strikes_[servo_id] < kLateStrikes) return false;
    late_probe_in_[servo_id] = std::chrono::milliseconds{0};
    scheduler_.silent(servo_id, SteadyClock::now(), next_late_probe(servo_id));
    reschedule_for_probe();
  }
  late_strikes_[servo_id] = 0;
  if (cache_.set_offline(servo_id, OfflineReason::AnswersLate) != OfflineReason::AnswersLate) {
    spdlog::warn(
        "bus {}: servo {} answers late (an answer came at least {} ms after it was asked; response_timeout_ms {}): "
        "offline: probed (again after {} ms, then less often, up to every {} ms) instead of retried at the other "
        "servos' cost; if it is that slow, raise response_timeout_ms",
        settings_.name, servo_id, after_asked.count(), settings_.response_timeout.count(), first_late_probe().count(),
        settings_.probe_period.count());
  }
  return true;
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::note_status(std::uint8_t servo_id, std::uint8_t status) {
  ServoCounters* counters = cache_.counters(servo_id);
  if (counters == nullptr) return;
  // One rule for every answer kind (status, data, acknowledgement, SYNC READ, a polled status
  // register): the refusal bits speak of the instruction just answered (the client learns of a
  // refusal from its result), the rest of the byte of the servo's condition — only the condition
  // is recorded and logged, once per change (docs/DECISIONS.md "Gateway", the status byte).
  // The bus thread is the only writer; logged before it shows, like every change of state here.
  const auto condition = static_cast<std::uint8_t>(status & ~transactor_->refusal_bits());
  const auto previous = counters->last_status.load(std::memory_order_relaxed);
  if (previous == condition) return;
  spdlog::info("bus {}: servo {} status byte 0x{:02X} -> 0x{:02X}", settings_.name, servo_id, previous, condition);
  counters->last_status.store(condition, std::memory_order_relaxed);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::note_timeout(std::uint8_t servo_id) {
  counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
  events_.unanswered(servo_id);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::note_written(const Request& request) {
  // Keeps the cached response levels true when a client changes one (REG WRITE takes effect
  // only at ACTION and is not followed).
  const auto apply = [this](std::uint8_t servo_id, std::uint16_t address, std::span<const std::uint8_t> data) {
    const ServoSettings* target = servo(servo_id);
    const IdentityLayout* layout = target == nullptr ? nullptr : identity_layout(target->table);
    const auto level_address = layout == nullptr ? std::nullopt : layout->response_level_address();
    if (!level_address || *level_address < address || *level_address >= address + data.size()) return;
    cache_.set_response_level(servo_id, data[*level_address - address]);
  };
  transactor_->for_each_write(request,
                              [&](std::uint8_t servo_id, std::uint16_t address, std::span<const std::uint8_t> data) {
                                if (!Transactor::broadcast_id(servo_id)) return apply(servo_id, address, data);
                                for (const auto& each : settings_.servos) apply(each.servo_id, address, data);
                              });
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::note_instructions(const Job& job) {
  if (settings_.protocol != protocol::BusProtocol::D55d) return;
  const auto now = SteadyClock::now();
  const auto heard = [&](std::uint8_t servo_id) {
    if (servo(servo_id) == nullptr) return;
    auto& last = last_instruction_[servo_id];
    if (last && now - *last > config::kD55dHeartbeat) {
      if (ServoCounters* counters = cache_.counters(servo_id)) {
        counters->heartbeat_gaps.fetch_add(1, std::memory_order_relaxed);
      }
      // Said once per motor at warning (a poll period longer than the heartbeat would repeat it
      // every cycle; --check-config warns of that one), then at debug; always counted.
      const auto level = heartbeat_gap_logged_.test(servo_id) ? spdlog::level::debug : spdlog::level::warn;
      heartbeat_gap_logged_.set(servo_id);
      spdlog::log(level,
                  "bus {}: d55d motor {} went {} ms without an instruction: if it was moving, its {} ms heartbeat "
                  "stopped it where it stood (goal := present position); counted in "
                  "sms_gateway_servo_heartbeat_gaps_total, further ones logged at debug",
                  settings_.name, servo_id, std::chrono::duration_cast<std::chrono::milliseconds>(now - *last).count(),
                  config::kD55dHeartbeat.count());
    }
    last = now;
  };
  if (Transactor::broadcast(job.request)) {
    for (const auto& each : settings_.servos) heard(each.servo_id);
    return;
  }
  heard(Transactor::target(job.request));
  for (const auto id : job.sync_read_ids) heard(id);
  transactor_->for_each_write(job.request, [&](std::uint8_t servo_id, std::uint16_t, std::span<const std::uint8_t>) {
    if (!Transactor::broadcast_id(servo_id)) heard(servo_id);
  });
}

// ==== what transactions report ====================================================================

template <BusTransactor Transactor>
void EngineCore<Transactor>::Events::answered(std::uint8_t servo_id, std::optional<std::uint8_t> status) {
  ServoCounters* counters = core_.cache_.counters(servo_id);
  if (counters == nullptr) return;
  counters->replies_ok.fetch_add(1, std::memory_order_relaxed);
  if (status) core_.note_status(servo_id, *status);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::Events::answered_in_time(std::uint8_t servo_id) {
  core_.late_strikes_[servo_id] = 0;
}

template <BusTransactor Transactor>
bool EngineCore<Transactor>::Events::late(std::uint8_t servo_id, std::chrono::milliseconds after_asked) {
  return core_.servo(servo_id) != nullptr && core_.servo_late(servo_id, after_asked);
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::Events::unanswered(std::uint8_t servo_id) {
  if (ServoCounters* counters = core_.cache_.counters(servo_id)) {
    counters->timeouts.fetch_add(1, std::memory_order_relaxed);
  }
}

template <BusTransactor Transactor>
void EngineCore<Transactor>::Events::sync_answer(std::uint8_t servo_id, std::span<const std::uint8_t> data) {
  // Only listed members' answers come here (the transactor judges the others not ours), and the
  // list is the poll plan's: configured servos.
  core_.sync_answered_.set(servo_id);
  if (core_.sync_collect_ != nullptr) {
    (*core_.sync_collect_)[servo_id] = protocol::Bytes(data.begin(), data.end());
  } else {
    core_.cache_.store_block(servo_id, data, SteadyClock::now());
  }
  core_.servo_answered(servo_id);
}

template class EngineCore<PacketTransactor>;
template class EngineCore<RtuTransactor>;

}  // namespace sms::gateway
