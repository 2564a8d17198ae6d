#include "gateway/bus/packet_bus_engine.h"

#include <pthread.h>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/posix/stream_descriptor.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <fmt/format.h>
#include <spdlog/fmt/bin_to_hex.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bitset>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <thread>
#include <utility>
#include <variant>

#include "gateway/bus/discovery.h"
#include "gateway/bus/job_queue.h"
#include "gateway/bus/packet_rules.h"
#include "gateway/bus/poll_scheduler.h"
#include "modbus_map/tables.h"
#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"
#include "protocol/stream_decoder.h"

namespace sms::gateway {
namespace asio = boost::asio;

namespace {

using namespace std::chrono_literals;
using protocol::Packet;

const PacketRules& rules_for(const BusSettings& settings) {
  if (settings.protocol == protocol::BusProtocol::ModbusRtu) {
    throw std::invalid_argument("bus " + settings.name + ": the packet bus engine drives feetech and d55d buses, not " +
                                std::string(protocol::to_string(settings.protocol)));
  }
  return packet_rules(settings.protocol);
}

struct Job {
  Packet request;
  ReplyKind reply = ReplyKind::None;
  std::uint8_t servo_id = protocol::kBroadcastId;
  std::uint8_t count = 0;  // Data, SyncRead: parameters expected per answer
  std::vector<std::uint8_t> sync_ids;
  unsigned attempts = 1;
  bool client = false;  // from submit(): holds a slot of the bounded queue, completes on every outcome
  MotionEpoch motion_epoch = 0;  // motion_refusal() just before the job goes on the wire
  SteadyClock::time_point queued_at{};  // when queued: the age rule of pop_job
  Completion done;
};

std::string join_ids(std::span<const std::uint8_t> ids) {
  std::string text;
  for (const auto id : ids) {
    if (!text.empty()) text += ',';
    text += std::to_string(id);
  }
  return text;
}

std::uint32_t saturate_us(SteadyClock::duration duration) {
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(duration).count();
  if (us < 0) return 0;
  return us > std::numeric_limits<std::uint32_t>::max() ? std::numeric_limits<std::uint32_t>::max()
                                                         : static_cast<std::uint32_t>(us);
}

double to_ms(std::chrono::nanoseconds duration) { return static_cast<double>(duration.count()) / 1e6; }

}  // namespace

class PacketBusEngine::Impl {
 public:
  explicit Impl(BusSettings settings);
  ~Impl();
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  void start();
  void stop();
  void submit(BusOp op, Priority priority, Completion done);

  const BusSettings& settings() const { return settings_; }
  bool bus_up() const { return bus_up_.load(); }
  BusCountersSnapshot counters() const { return counters_.snapshot(); }
  const PollCache& cache() const { return cache_; }
  bool discovered() const { return discovered_.load(); }

 private:
  struct Active {
    explicit Active(Job j) : job(std::move(j)) {}
    Job job;
    protocol::Bytes frame;  // encoded once, sent on every attempt
    unsigned attempt = 0;
    std::size_t frames_this_attempt = 0;
    std::optional<Packet> echo_candidate;
    bool damaged_any = false;        // a damaged frame came back on some attempt
    bool quiet_wait = false;         // after a damaged answer: waiting for the line to go quiet
    bool refused_damaged = false;    // d55d checksum bit seen
    std::uint8_t last_error = 0;
    SteadyClock::time_point sent_at;
    SteadyClock::time_point deadline;
    SteadyClock::time_point original_deadline;
    std::chrono::nanoseconds attempt_timeout{};  // for messages
    std::bitset<256> sync_expected;
    std::bitset<256> sync_answered;
  };

  // --- building jobs ------------------------------------------------------------------------
  Job make_client_job(BusOp&& op) const;
  Job read_job(std::uint8_t servo_id, AddressBlock block, unsigned attempts) const;
  Job sync_read_job(AddressBlock block, std::vector<std::uint8_t> ids) const;
  std::string describe(const Job& job) const;

  // --- queue ----------------------------------------------------------------------------------
  std::optional<Job> pop_job();
  void enqueue_internal(Job job);
  void kick();

  // --- transactions (bus thread) ----------------------------------------------------------------
  void start_next();
  void begin_attempt();
  void arm_deadline(SteadyClock::time_point deadline);
  void wait_for_reply();
  void on_readable(std::uint64_t token, const boost::system::error_code& error);
  void on_deadline(std::uint64_t token, const boost::system::error_code& error);
  bool read_pending(std::uint64_t token);
  void process_events();
  void handle_frame(Packet frame);
  Verdict judge(const Active& active, const Packet& frame) const;
  void accept_answer(Packet frame);
  void attempt_failed(bool no_answer);
  void finish(BusStatus status, std::uint8_t servo_error, protocol::Bytes data, std::string detail);
  void note_answer(std::uint8_t servo_id, std::uint8_t error);
  void note_timeout(std::uint8_t servo_id);
  void note_written(const Packet& request);
  void sync_discarded();
  std::chrono::nanoseconds reply_allowance(std::size_t reply_bytes) const;
  bool addressed_servo_offline(const Job& job) const;

  // --- port ---------------------------------------------------------------------------------------
  Expected<Ok> open_port();
  void close_port();
  std::vector<Job> take_client_jobs();
  std::optional<Active> abandon_active();
  void port_lost(const std::string& reason);
  void schedule_reopen();
  void try_reopen();
  void shutdown();
  void run_thread();

  // --- discovery and polling ------------------------------------------------------------------------
  void begin_discovery();
  void on_discovery_ping(std::size_t index, const BusResult& result);
  void on_discovery_identity(std::size_t index, const BusResult& result);
  void discovery_step_done();
  void read_identity(std::uint8_t servo_id, std::optional<std::size_t> discovery_index);
  void start_poll_cycle();
  void enqueue_poll_read(std::uint8_t servo_id, bool probe);
  void on_poll_read(std::uint8_t servo_id, bool probe, const BusResult& result);
  void on_sync_read_finished(const Active& active);
  void poll_job_done();
  void schedule_poll(SteadyClock::time_point when);
  void servo_answered(std::uint8_t servo_id);
  void servo_silent(std::uint8_t servo_id, const std::string& reason, bool log);
  const ServoSettings* servo(std::uint8_t servo_id) const;

  BusSettings settings_;
  const PacketRules& rules_;
  PollCache cache_;
  BusCounters counters_;
  PollScheduler scheduler_;
  std::chrono::nanoseconds quiet_gap_;
  std::array<std::chrono::nanoseconds, kPriorityCount> age_limits_;  // per Priority, see pop_job

  asio::io_context io_{1};
  asio::executor_work_guard<asio::io_context::executor_type> work_;
  asio::posix::stream_descriptor descriptor_;
  asio::steady_timer attempt_timer_;
  asio::steady_timer poll_timer_;
  asio::steady_timer reopen_timer_;
  std::thread thread_;

  SerialPort port_;
  protocol::StreamDecoder decoder_;
  std::size_t decoder_discarded_seen_ = 0;
  std::array<std::uint8_t, 512> rx_buffer_{};

  // Shared with submitting threads.
  std::mutex queue_mutex_;
  JobQueue<Job> queue_;
  bool accepting_ = false;
  std::atomic<bool> bus_up_{false};
  std::atomic<bool> discovered_{false};

  // Bus thread only.
  std::optional<Active> active_;
  std::uint64_t token_ = 0;  // changes whenever an attempt starts or ends: stale handlers see it
  struct Cycle {
    bool running = false;
    SteadyClock::time_point started;
    std::size_t outstanding = 0;
  } cycle_;
  struct Discovery {
    std::vector<DiscoveredServo> servos;
    std::size_t pending = 0;
  } discovery_;
  std::bitset<256> identity_known_;
  std::bitset<256> poll_refusal_logged_;
  bool open_failure_logged_ = false;
};

// ==== construction ======================================================================

namespace {

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

const BusSettings& validated(const BusSettings& settings) {
  const std::string where = "bus " + settings.name + ": ";
  if (settings.serial.baud == 0) throw std::invalid_argument(where + "baud must not be 0");
  if (settings.queue_depth == 0) throw std::invalid_argument(where + "queue depth must be at least 1");
  for (const auto& servo : settings.servos) {
    const auto& table = modbus_map::table(servo.table);
    const std::string who = where + "servo " + std::to_string(servo.servo_id) + " (" + std::string(table.name) + "): ";
    if (table.protocol != settings.protocol) {
      throw std::invalid_argument(who + "its table is spoken over " + std::string(protocol::to_string(table.protocol)) +
                                  ", not over this " + std::string(protocol::to_string(settings.protocol)) + " bus");
    }
    const auto& block = servo.poll_block;
    if (block.count == 0 || block.count > protocol::kMaxParams || block.address > 0xFF || block.end() > 0x100) {
      throw std::invalid_argument(who + "poll block " + std::to_string(block.address) + "+" +
                                  std::to_string(block.count) +
                                  " cannot be read in one READ (byte addresses 0-255, 1-253 bytes)");
    }
  }
  return settings;
}

}  // namespace

PacketBusEngine::Impl::Impl(BusSettings settings)
    : settings_(std::move(settings)),
      rules_(rules_for(validated(settings_))),
      cache_(cache_entries(settings_)),
      scheduler_(poll_targets(settings_, rules_.has_sync_read), settings_.probe_period),
      quiet_gap_(wire_time(settings_.serial, 32) + 1ms),
      age_limits_{std::chrono::nanoseconds{0}, kClientAgeLimit, kClientAgeLimit,
                  std::max<std::chrono::nanoseconds>(settings_.poll_period, 10ms)},
      work_(asio::make_work_guard(io_)),
      descriptor_(io_),
      attempt_timer_(io_),
      poll_timer_(io_),
      reopen_timer_(io_),
      port_(settings_.serial),
      decoder_(*rules_.format) {}

PacketBusEngine::Impl::~Impl() { stop(); }

// ==== jobs ================================================================================

Job PacketBusEngine::Impl::read_job(std::uint8_t servo_id, AddressBlock block, unsigned attempts) const {
  Job job;
  job.request = protocol::read(servo_id, static_cast<std::uint8_t>(block.address), static_cast<std::uint8_t>(block.count));
  job.reply = ReplyKind::Data;
  job.servo_id = servo_id;
  job.count = static_cast<std::uint8_t>(block.count);
  job.attempts = attempts;
  return job;
}

Job PacketBusEngine::Impl::sync_read_job(AddressBlock block, std::vector<std::uint8_t> ids) const {
  Job job;
  job.request = protocol::feetech::sync_read(static_cast<std::uint8_t>(block.address),
                                             static_cast<std::uint8_t>(block.count), ids);
  job.reply = ReplyKind::SyncRead;
  job.count = static_cast<std::uint8_t>(block.count);
  job.sync_ids = std::move(ids);
  job.attempts = 1;  // who stays silent is read on its own, with retries (on_sync_read_finished)
  return job;
}

Job PacketBusEngine::Impl::make_client_job(BusOp&& op) const {
  const unsigned attempts = 1 + settings_.retries;
  const std::string where = "bus " + settings_.name + ": ";
  auto require = [&](bool condition, const std::string& what) {
    if (!condition) throw std::invalid_argument(where + what);
  };
  Job job;
  job.client = true;
  job.attempts = attempts;
  if (auto* read = std::get_if<ReadOp>(&op)) {
    require(read->servo_id < protocol::kBroadcastId, "READ needs one servo ID (0-253), not the broadcast ID");
    require(read->address <= 0xFF, "READ address " + std::to_string(read->address) + " is not a byte address");
    require(read->count >= 1 && read->count <= protocol::kMaxParams,
            "READ of " + std::to_string(read->count) + " bytes: one READ returns 1-253 bytes");
    job = read_job(read->servo_id, {read->address, read->count}, attempts);
  } else if (auto* write = std::get_if<WriteOp>(&op)) {
    require(write->address <= 0xFF, "WRITE address " + std::to_string(write->address) + " is not a byte address");
    require(!write->data.empty() && write->data.size() < protocol::kMaxParams,
            "WRITE of " + std::to_string(write->data.size()) + " bytes: one WRITE carries 1-252 bytes");
    const auto address = static_cast<std::uint8_t>(write->address);
    job.request = write->staged ? protocol::reg_write(write->servo_id, address, write->data)
                                : protocol::write(write->servo_id, address, write->data);
    job.servo_id = write->servo_id;
    // Broadcast writes are never answered (SPEC §1).
    job.reply = (write->expect_reply && write->servo_id != protocol::kBroadcastId) ? ReplyKind::Ack : ReplyKind::None;
  } else if (std::holds_alternative<ActionOp>(op)) {
    job.request = protocol::action();
  } else if (auto* sync = std::get_if<SyncWriteOp>(&op)) {
    require(sync->address <= 0xFF, "SYNC WRITE address " + std::to_string(sync->address) + " is not a byte address");
    require(!sync->entries.empty(), "SYNC WRITE without servos");
    try {
      job.request = protocol::sync_write(static_cast<std::uint8_t>(sync->address), sync->length, sync->entries);
    } catch (const std::exception& error) {
      throw std::invalid_argument(where + "SYNC WRITE: " + error.what());
    }
  } else if (auto* ping = std::get_if<PingOp>(&op)) {
    require(ping->servo_id < protocol::kBroadcastId, "PING needs one servo ID (0-253): answers to a broadcast collide");
    job.request = protocol::ping(ping->servo_id);
    job.servo_id = ping->servo_id;
    job.reply = ReplyKind::Ping;
  } else {
    throw std::invalid_argument(where + "a raw Modbus PDU cannot be sent on a " +
                                std::string(protocol::to_string(settings_.protocol)) + " bus");
  }
  job.client = true;
  return job;
}

std::string PacketBusEngine::Impl::describe(const Job& job) const {
  const auto name = rules_.instruction_name(job.request.code).value_or("instruction");
  const auto& params = job.request.params;
  switch (job.reply) {
    case ReplyKind::Data:
      return fmt::format("{} {}+{} of servo {}", name, params.at(0), params.at(1), job.servo_id);
    case ReplyKind::Ack:
      return fmt::format("{} at {} ({} bytes) to servo {}", name, params.at(0), params.size() - 1, job.servo_id);
    case ReplyKind::Ping:
      return fmt::format("{} of servo {}", name, job.servo_id);
    case ReplyKind::SyncRead:
      return fmt::format("{} {}+{} of servos {}", name, params.at(0), params.at(1), join_ids(job.sync_ids));
    case ReplyKind::None:
      break;
  }
  if (job.servo_id == protocol::kBroadcastId) return fmt::format("broadcast {}", name);
  return fmt::format("{} to servo {} (not answered)", name, job.servo_id);
}

// ==== queue ===============================================================================

void PacketBusEngine::Impl::submit(BusOp op, Priority priority, Completion done) {
  const MotionEpoch motion_epoch = motion_epoch_of(op);
  Job job = make_client_job(std::move(op));
  job.motion_epoch = motion_epoch;
  job.done = std::move(done);
  if (queue_client_job(settings_, counters_, queue_mutex_, queue_, std::move(job), priority, accepting_, bus_up_.load())) {
    kick();
  }
}

std::optional<Job> PacketBusEngine::Impl::pop_job() {
  std::lock_guard lock(queue_mutex_);
  // next_level() (bus_engine.h): safe stops first; then whatever waited past its age limit,
  // oldest first — client work after kClientAgeLimit, the engine's own poll, probe or discovery
  // transaction after one poll period (at least 10 ms), so neither a flood of writes can starve
  // a live read nor a flood of live requests freeze the poll cache (FC04) or keep an offline
  // servo from its probe; else strict priority. Jobs of one poll cycle are queued together, so
  // the rest of the cycle follows.
  const auto level = queue_.next(age_limits_, SteadyClock::now());
  if (!level) return std::nullopt;
  return queue_.pop(*level);
}

void PacketBusEngine::Impl::enqueue_internal(Job job) {
  {
    std::lock_guard lock(queue_mutex_);
    queue_.push_internal(std::move(job), Priority::Poll);
  }
  kick();
}

void PacketBusEngine::Impl::kick() {
  asio::post(io_, [this] { start_next(); });
}

// ==== transactions ==========================================================================

bool PacketBusEngine::Impl::addressed_servo_offline(const Job& job) const {
  if (job.servo_id == protocol::kBroadcastId) return false;
  return scheduler_.presence(job.servo_id) == Presence::Offline;
}

void PacketBusEngine::Impl::start_next() {
  while (!active_ && port_.is_open()) {
    std::optional<Job> job = pop_job();
    if (!job) return;
    if (auto refusal = motion_refusal(settings_, job->motion_epoch)) {
      complete(settings_, job->done, std::move(*refusal));
      continue;
    }
    if (job->client && addressed_servo_offline(*job)) {
      counters_.transactions.fetch_add(1, std::memory_order_relaxed);
      const auto detail = fmt::format("bus {}: servo {} is offline (it stopped answering; probed every {} ms)",
                                      settings_.name, job->servo_id, settings_.probe_period.count());
      complete(settings_, job->done, BusResult{BusStatus::Timeout, 0, {}, detail});
      continue;
    }
    active_.emplace(std::move(*job));
    active_->frame = protocol::encode(*rules_.format, active_->job.request);
    for (const auto id : active_->job.sync_ids) active_->sync_expected.set(id);
    begin_attempt();
  }
}

std::chrono::nanoseconds PacketBusEngine::Impl::reply_allowance(std::size_t reply_bytes) const {
  return wire_time(settings_.serial, reply_bytes) + settings_.response_timeout;
}

void PacketBusEngine::Impl::begin_attempt() {
  Active& active = *active_;
  ++active.attempt;
  ++token_;
  if (active.attempt > 1) counters_.retries.fetch_add(1, std::memory_order_relaxed);
  active.frames_this_attempt = 0;
  active.echo_candidate.reset();
  active.quiet_wait = false;

  const auto flushed = port_.discard_input();
  if (!flushed) return port_lost(flushed.error());
  counters_.discarded_bytes.fetch_add(*flushed, std::memory_order_relaxed);
  decoder_.reset();
  sync_discarded();

  if (spdlog::should_log(spdlog::level::trace)) {
    spdlog::trace("bus {}: tx {}", settings_.name, spdlog::to_hex(active.frame));
  }
  active.sent_at = SteadyClock::now();
  const auto request_time = wire_time(settings_.serial, active.frame.size());
  const auto written = port_.write_all(
      active.frame, settings_.response_timeout + std::chrono::ceil<std::chrono::milliseconds>(request_time) + 50ms);
  if (!written) return port_lost(written.error());

  const Job& job = active.job;
  if (job.reply == ReplyKind::None) {
    // Broadcast or unanswered write: complete once it is on the wire.
    const auto drained = port_.drain();
    if (!drained) return port_lost(drained.error());
    const auto on_wire = active.sent_at + request_time;
    if (SteadyClock::now() >= on_wire) return finish(BusStatus::Ok, 0, {}, {});
    attempt_timer_.expires_at(on_wire);
    attempt_timer_.async_wait([this, token = token_](const boost::system::error_code& error) {
      if (error || token != token_ || !active_) return;
      finish(BusStatus::Ok, 0, {}, {});
    });
    return;
  }
  std::size_t reply_bytes = protocol::kMinFrameSize;
  if (job.reply == ReplyKind::Data || job.reply == ReplyKind::SyncRead) reply_bytes += job.count;
  if (job.reply == ReplyKind::Ping) reply_bytes += rules_.max_ping_params;
  active.attempt_timeout = request_time + reply_allowance(reply_bytes);
  const auto deadline = active.sent_at + active.attempt_timeout;
  active.original_deadline = deadline;
  arm_deadline(deadline);
  wait_for_reply();
}

void PacketBusEngine::Impl::arm_deadline(SteadyClock::time_point deadline) {
  active_->deadline = deadline;
  attempt_timer_.expires_at(deadline);
  attempt_timer_.async_wait(
      [this, token = token_](const boost::system::error_code& error) { on_deadline(token, error); });
}

void PacketBusEngine::Impl::wait_for_reply() {
  descriptor_.async_wait(asio::posix::stream_descriptor::wait_read,
                         [this, token = token_](const boost::system::error_code& error) { on_readable(token, error); });
}

void PacketBusEngine::Impl::on_readable(std::uint64_t token, const boost::system::error_code& error) {
  if (error == asio::error::operation_aborted || token != token_ || !active_) return;
  if (error) return port_lost("waiting for " + settings_.serial.device + ": " + error.message());
  if (!read_pending(token) || token != token_) return;  // port lost, finished, or a new attempt
  wait_for_reply();
}

// Reads and decodes what the port holds now. False when the port was lost (already handled).
bool PacketBusEngine::Impl::read_pending(std::uint64_t token) {
  for (;;) {
    const auto received = port_.read_available(rx_buffer_);
    if (!received) {
      port_lost(received.error());
      return false;
    }
    if (*received == 0) return true;
    const std::span<const std::uint8_t> bytes(rx_buffer_.data(), *received);
    if (spdlog::should_log(spdlog::level::trace)) spdlog::trace("bus {}: rx {}", settings_.name, spdlog::to_hex(bytes));
    decoder_.feed(bytes);
    if (active_->quiet_wait) {
      // Bytes still arriving after a damaged answer: wait until the line is quiet.
      arm_deadline(std::min(active_->original_deadline, SteadyClock::now() + quiet_gap_));
    }
    process_events();
    sync_discarded();
    if (token != token_) return true;  // finished, or a new attempt is under way
    // A short read emptied the tty's buffer: what arrives later raises a new readiness edge,
    // so the extra read() that would say EAGAIN is skipped.
    if (*received < rx_buffer_.size()) return true;
  }
}

void PacketBusEngine::Impl::on_deadline(std::uint64_t token, const boost::system::error_code& error) {
  if (error || token != token_ || !active_) return;
  // When this thread ran late (a busy machine), the answer may be waiting in the port while
  // the timer's handler runs first: read it before calling the attempt failed.
  if (!read_pending(token) || token != token_ || !active_) return;
  if (SteadyClock::now() < active_->deadline) return;  // bytes of a damaged answer moved the deadline
  boost::system::error_code ignored;
  descriptor_.cancel(ignored);  // this attempt's readiness wait
  Active& active = *active_;
  if (active.echo_candidate) {
    // What looked like our own echo was the only frame: it was the answer after all.
    Packet answer = std::move(*active.echo_candidate);
    active.echo_candidate.reset();
    return accept_answer(std::move(answer));
  }
  attempt_failed(true);
}

void PacketBusEngine::Impl::process_events() {
  const std::uint64_t token = token_;
  while (active_ && token == token_) {
    auto event = decoder_.next();
    if (!event) return;
    if (event->kind == protocol::DecodeEvent::Kind::Frame) {
      handle_frame(std::move(event->packet));
      continue;
    }
    // A damaged frame (checksum, or a LEN no frame can have).
    counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
    Active& active = *active_;
    active.damaged_any = true;
    if (active.job.reply != ReplyKind::SyncRead && event->packet.id == active.job.servo_id && !active.quiet_wait) {
      // Our servo's answer arrived damaged: no valid one follows. Retry as soon as the line is
      // quiet (transmitting into the tail of a frame would collide on a half-duplex bus).
      active.quiet_wait = true;
      arm_deadline(std::min(active.original_deadline, SteadyClock::now() + quiet_gap_));
    }
  }
}

Verdict PacketBusEngine::Impl::judge(const Active& active, const Packet& frame) const {
  const Job& job = active.job;
  if (job.reply == ReplyKind::SyncRead &&
      (!active.sync_expected.test(frame.id) || active.sync_answered.test(frame.id))) {
    return Verdict::NotOurs;
  }
  return judge_reply(rules_, job.reply, job.servo_id, job.count, frame);
}

void PacketBusEngine::Impl::handle_frame(Packet frame) {
  Active& active = *active_;
  const Verdict verdict = judge(active, frame);
  const bool first = active.frames_this_attempt++ == 0;
  if (verdict == Verdict::Answer && first && frame == active.job.request) {
    // Byte for byte our request: an adapter echoing what we sent. Hold it; it is the answer
    // only if nothing else comes before the deadline.
    active.echo_candidate = std::move(frame);
    return;
  }
  switch (verdict) {
    case Verdict::NotOurs:
      counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
      if (spdlog::should_log(spdlog::level::debug)) {
        spdlog::debug("bus {}: ignored a frame from ID {} (ERROR 0x{:02X}, {} bytes) while waiting for {}", settings_.name,
                      frame.id, frame.code, frame.params.size(), describe(active.job));
      }
      return;
    case Verdict::Answer:
      if (active.echo_candidate) {
        counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
        active.echo_candidate.reset();
      }
      return accept_answer(std::move(frame));
    case Verdict::Refused:
      note_answer(frame.id, frame.code);
      return finish(BusStatus::ServoRefused, frame.code, {},
                    fmt::format("bus {}: servo {} refused {} (ERROR 0x{:02X})", settings_.name, frame.id,
                                describe(active.job), frame.code));
    case Verdict::RefusedDamaged:
      note_answer(frame.id, frame.code);
      active.refused_damaged = true;
      active.last_error = frame.code;
      attempt_timer_.cancel();
      return attempt_failed(false);
  }
}

void PacketBusEngine::Impl::accept_answer(Packet frame) {
  Active& active = *active_;
  counters_.frames_ok.fetch_add(1, std::memory_order_relaxed);
  note_answer(frame.id, frame.code);
  if (active.job.reply != ReplyKind::SyncRead) return finish(BusStatus::Ok, frame.code, std::move(frame.params), {});

  active.sync_answered.set(frame.id);
  if (const ServoSettings* answered = servo(frame.id)) {
    cache_.store_block(frame.id, frame.params, SteadyClock::now());
    servo_answered(answered->servo_id);
  }
  if (active.sync_answered == active.sync_expected) return finish(BusStatus::Ok, 0, {}, {});
  // The next servo in the list answers after this one (SPEC §1.1): restart the wait.
  arm_deadline(SteadyClock::now() + reply_allowance(protocol::kMinFrameSize + active.job.count));
}

void PacketBusEngine::Impl::attempt_failed(bool no_answer) {
  Active& active = *active_;
  const Job& job = active.job;
  if (job.reply == ReplyKind::SyncRead) return finish(BusStatus::Ok, 0, {}, {});  // the missing are followed up
  if (no_answer) note_timeout(job.servo_id);
  if (active.attempt < job.attempts) return begin_attempt();

  const auto attempts = fmt::format("{} attempt{}", job.attempts, job.attempts == 1 ? "" : "s");
  if (active.refused_damaged) {
    return finish(BusStatus::ServoRefused, active.last_error, {},
                  fmt::format("bus {}: servo {} reported our {} as damaged (ERROR 0x{:02X}) after {}", settings_.name,
                              job.servo_id, describe(job), active.last_error, attempts));
  }
  if (active.damaged_any) {
    return finish(BusStatus::Corrupt, 0, {},
                  fmt::format("bus {}: only damaged answers to {} after {} (checksum or framing errors)",
                              settings_.name, describe(job), attempts));
  }
  finish(BusStatus::Timeout, 0, {},
         fmt::format("bus {}: no answer to {} after {} of {:.1f} ms", settings_.name, describe(job), attempts,
                     to_ms(active.attempt_timeout)));
}

void PacketBusEngine::Impl::finish(BusStatus status, std::uint8_t servo_error, protocol::Bytes data,
                                   std::string detail) {
  Active active = std::move(*active_);
  active_.reset();
  ++token_;
  attempt_timer_.cancel();
  counters_.transactions.fetch_add(1, std::memory_order_relaxed);
  if (status == BusStatus::Ok) {
    note_written(active.job.request);
  } else {
    spdlog::debug("{}", detail);
  }
  if (active.job.reply == ReplyKind::SyncRead) {
    on_sync_read_finished(active);
  } else {
    complete(settings_, active.job.done, BusResult{status, servo_error, std::move(data), std::move(detail)});
  }
  kick();
}

void PacketBusEngine::Impl::note_answer(std::uint8_t servo_id, std::uint8_t error) {
  ServoCounters* counters = cache_.counters(servo_id);
  if (counters == nullptr) return;
  counters->replies_ok.fetch_add(1, std::memory_order_relaxed);
  // One rule for every answer kind (status, data, acknowledgement, SYNC READ): the refusal bits
  // speak of the instruction just answered (and the client learns of a refusal from its result),
  // the rest of the byte of the servo's condition — only the condition is recorded and logged, so
  // a servo that sets a refusal bit in every answer does not flip register 1000 between polls
  // and writes (docs/DECISIONS.md "Gateway").
  const auto condition = static_cast<std::uint8_t>(error & ~rules_.refusal_bits);
  const auto previous = counters->last_status.exchange(condition, std::memory_order_relaxed);
  if (previous != condition) {
    spdlog::info("bus {}: servo {} status byte 0x{:02X} -> 0x{:02X}", settings_.name, servo_id, previous, condition);
  }
}

void PacketBusEngine::Impl::note_timeout(std::uint8_t servo_id) {
  counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
  if (ServoCounters* counters = cache_.counters(servo_id)) counters->timeouts.fetch_add(1, std::memory_order_relaxed);
}

void PacketBusEngine::Impl::note_written(const Packet& request) {
  // Keeps the cached response levels true when a client changes one (REG WRITE takes effect
  // only at ACTION and is not followed).
  const auto apply = [this](std::uint8_t servo_id, std::uint8_t address, std::span<const std::uint8_t> data) {
    const ServoSettings* target = servo(servo_id);
    const IdentityLayout* layout = target == nullptr ? nullptr : identity_layout(target->table);
    const auto level_address = layout == nullptr ? std::nullopt : layout->response_level_address();
    if (!level_address || *level_address < address || *level_address >= address + data.size()) return;
    cache_.set_response_level(servo_id, data[*level_address - address]);
  };
  if (request.code == protocol::common::kWrite && request.params.size() >= 2) {
    const auto data = std::span<const std::uint8_t>(request.params).subspan(1);
    if (request.id != protocol::kBroadcastId) return apply(request.id, request.params[0], data);
    for (const auto& each : settings_.servos) apply(each.servo_id, request.params[0], data);
  } else if (request.code == protocol::common::kSyncWrite) {
    if (const auto sync = protocol::parse_sync_write(request.params)) {
      for (const auto& entry : sync->entries) apply(entry.id, sync->address, entry.data);
    }
  }
}

void PacketBusEngine::Impl::sync_discarded() {
  const auto total = decoder_.discarded_bytes();
  counters_.discarded_bytes.fetch_add(total - decoder_discarded_seen_, std::memory_order_relaxed);
  decoder_discarded_seen_ = total;
}

// ==== port =================================================================================

Expected<Ok> PacketBusEngine::Impl::open_port() {
  auto opened = port_.open();
  if (!opened) return opened;
  descriptor_.assign(port_.native_handle());
  const auto wanted = settings_.serial.baud;
  const auto actual = port_.actual_baud();
  if (actual != wanted && (actual > wanted ? actual - wanted : wanted - actual) * 100 > wanted) {
    spdlog::warn("bus {}: {} runs at {} bit/s instead of {} (the adapter rounds this rate): frames may be garbled",
                 settings_.name, settings_.serial.device, actual, wanted);
  }
  decoder_.reset();
  sync_discarded();
  {
    std::lock_guard lock(queue_mutex_);
    bus_up_.store(true);
  }
  open_failure_logged_ = false;
  spdlog::info("bus {}: {} open, {} at {} bit/s, {} parity, {} stop bit{}", settings_.name, settings_.serial.device,
               rules_.format->name, wanted, config::to_string(settings_.serial.parity), settings_.serial.stop_bits,
               settings_.serial.stop_bits == 1 ? "" : "s");
  begin_discovery();
  return Ok{};
}

void PacketBusEngine::Impl::close_port() {
  if (descriptor_.is_open()) descriptor_.release();  // the port owns the fd and closes it
  port_.close();
}

// Empties the queue and marks the bus down; returns the client jobs, which must be answered.
// Poll and discovery work is dropped: it is rebuilt when the bus is back.
std::vector<Job> PacketBusEngine::Impl::take_client_jobs() {
  std::lock_guard lock(queue_mutex_);
  bus_up_.store(false);
  return queue_.take_clients();
}

// Forgets the transaction on the wire: its reply and its timer can no longer complete it.
std::optional<PacketBusEngine::Impl::Active> PacketBusEngine::Impl::abandon_active() {
  std::optional<Active> interrupted = std::move(active_);
  active_.reset();
  ++token_;
  attempt_timer_.cancel();
  poll_timer_.cancel();
  return interrupted;
}

void PacketBusEngine::Impl::port_lost(const std::string& reason) {
  if (!port_.is_open()) return;
  spdlog::error("bus {}: {} — bus down; reopening every {} ms", settings_.name, reason, settings_.reopen_period.count());
  close_port();
  counters_.bus_down_events.fetch_add(1, std::memory_order_relaxed);
  // Before the bus reads down: whoever sees bus_up() false sees every servo offline too.
  cache_.set_all_offline();
  discovered_.store(false);

  std::vector<Job> failed = take_client_jobs();
  std::optional<Active> interrupted = abandon_active();
  scheduler_.forget_all();
  cycle_ = Cycle{};
  discovery_ = Discovery{};

  const std::string detail = "bus " + settings_.name + ": " + reason;
  if (interrupted && interrupted->job.client) {
    counters_.transactions.fetch_add(1, std::memory_order_relaxed);
    complete(settings_, interrupted->job.done, BusResult{BusStatus::BusDown, 0, {}, detail});
  }
  for (auto& job : failed) complete(settings_, job.done, BusResult{BusStatus::BusDown, 0, {}, detail});
  schedule_reopen();
}

void PacketBusEngine::Impl::schedule_reopen() {
  reopen_timer_.expires_after(settings_.reopen_period);
  reopen_timer_.async_wait([this](const boost::system::error_code& error) {
    if (!error) try_reopen();
  });
}

void PacketBusEngine::Impl::try_reopen() {
  {
    std::lock_guard lock(queue_mutex_);
    if (!accepting_) return;
  }
  if (port_.is_open()) return;
  const auto opened = open_port();
  if (opened) return;
  if (!open_failure_logged_) {
    spdlog::error("bus {}: {}; retrying every {} ms", settings_.name, opened.error(), settings_.reopen_period.count());
    open_failure_logged_ = true;
  } else {
    spdlog::debug("bus {}: still cannot open: {}", settings_.name, opened.error());
  }
  schedule_reopen();
}

void PacketBusEngine::Impl::start() {
  {
    std::lock_guard lock(queue_mutex_);
    if (accepting_ || thread_.joinable()) throw std::logic_error("bus " + settings_.name + ": started twice");
    accepting_ = true;
  }
  // Opened here, before the thread runs, so bus_up() is true on return when the port exists.
  try_reopen();
  thread_ = std::thread([this] { run_thread(); });
}

void PacketBusEngine::Impl::run_thread() {
  // "bus <name>" in top -H / gdb; Linux limits thread names to 15 characters.
  ::pthread_setname_np(::pthread_self(), ("bus " + settings_.name).substr(0, 15).c_str());
  for (;;) {
    try {
      io_.run();
      return;
    } catch (const std::exception& error) {
      spdlog::critical("bus {}: internal error on the bus thread: {}", settings_.name, error.what());
    }
  }
}

void PacketBusEngine::Impl::stop() {
  {
    std::lock_guard lock(queue_mutex_);
    accepting_ = false;
  }
  if (!thread_.joinable()) return;
  if (std::this_thread::get_id() == thread_.get_id()) {
    throw std::logic_error("bus " + settings_.name + ": stop() called from the bus thread (inside a completion)");
  }
  asio::post(io_, [this] { shutdown(); });
  thread_.join();
}

void PacketBusEngine::Impl::shutdown() {
  close_port();
  std::vector<Job> cancelled = take_client_jobs();
  std::optional<Active> interrupted = abandon_active();
  reopen_timer_.cancel();
  const std::string detail = "bus " + settings_.name + ": the gateway is stopping";
  if (interrupted && interrupted->job.client) complete(settings_, interrupted->job.done, BusResult{BusStatus::Cancelled, 0, {}, detail});
  for (auto& job : cancelled) complete(settings_, job.done, BusResult{BusStatus::Cancelled, 0, {}, detail});
  work_.reset();
  io_.stop();
}

// ==== discovery ===============================================================================

const ServoSettings* PacketBusEngine::Impl::servo(std::uint8_t servo_id) const {
  for (const auto& servo : settings_.servos) {
    if (servo.servo_id == servo_id) return &servo;
  }
  return nullptr;
}

void PacketBusEngine::Impl::begin_discovery() {
  discovered_.store(false);
  discovery_ = Discovery{};
  for (const auto& servo : settings_.servos) {
    DiscoveredServo found;
    found.servo_id = servo.servo_id;
    found.table = servo.table;
    discovery_.servos.push_back(std::move(found));
  }
  if (!settings_.discover || settings_.servos.empty()) {
    discovered_.store(true);
    if (settings_.poll) schedule_poll(SteadyClock::now());
    return;
  }
  for (std::size_t index = 0; index < settings_.servos.size(); ++index) {
    Job job;
    job.request = protocol::ping(settings_.servos[index].servo_id);
    job.reply = ReplyKind::Ping;
    job.servo_id = settings_.servos[index].servo_id;
    job.attempts = 1 + settings_.retries;
    job.done = [this, index](BusResult result) { on_discovery_ping(index, result); };
    ++discovery_.pending;
    enqueue_internal(std::move(job));
  }
}

void PacketBusEngine::Impl::on_discovery_ping(std::size_t index, const BusResult& result) {
  DiscoveredServo& found = discovery_.servos.at(index);
  if (result.status == BusStatus::Ok) {
    found.online = true;
    found.status = result.servo_error;
    servo_answered(found.servo_id);
    if (identity_layout(found.table) != nullptr) read_identity(found.servo_id, index);
  } else {
    found.detail = result.status == BusStatus::Timeout
                       ? fmt::format("no answer to PING ({} attempts)", 1 + settings_.retries)
                       : fmt::format("{} answering PING", to_string(result.status));
    servo_silent(found.servo_id, found.detail, false);
  }
  discovery_step_done();
}

void PacketBusEngine::Impl::read_identity(std::uint8_t servo_id, std::optional<std::size_t> discovery_index) {
  const ServoSettings* settings = servo(servo_id);
  const IdentityLayout* layout = settings == nullptr ? nullptr : identity_layout(settings->table);
  if (layout == nullptr) return;
  Job job = read_job(servo_id, layout->read, 1 + settings_.retries);
  job.done = [this, servo_id, discovery_index, layout, order = settings->byte_order](BusResult result) {
    if (result.status == BusStatus::Ok) {
      const ServoIdentity identity = decode_identity(*layout, result.data, order);
      cache_.set_identity(servo_id, identity);
      cache_.set_response_level(servo_id, decode_response_level(*layout, result.data));
      identity_known_.set(servo_id);
      if (discovery_index) discovery_.servos.at(*discovery_index).identity = identity;
    }
    if (discovery_index) discovery_step_done();
  };
  if (discovery_index) ++discovery_.pending;
  enqueue_internal(std::move(job));
}

void PacketBusEngine::Impl::discovery_step_done() {
  if (discovery_.pending == 0 || --discovery_.pending > 0) return;
  spdlog::info("{}", format_discovery_summary({settings_.name, settings_.serial.device, rules_.format->name,
                                               settings_.serial.baud, discovery_.servos}));
  discovered_.store(true);
  if (settings_.poll) schedule_poll(SteadyClock::now());
}

// ==== polling =============================================================================

void PacketBusEngine::Impl::schedule_poll(SteadyClock::time_point when) {
  if (when <= SteadyClock::now()) {
    // Already due (back-to-back polling, or a cycle longer than the period): start it now. A
    // timer armed for the past would still cost a sleep and a wake-up of this thread between
    // two cycles, bus time lost on every cycle.
    poll_timer_.cancel();
    return start_poll_cycle();
  }
  poll_timer_.expires_at(when);
  poll_timer_.async_wait([this](const boost::system::error_code& error) {
    if (!error) start_poll_cycle();
  });
}

void PacketBusEngine::Impl::start_poll_cycle() {
  if (!port_.is_open() || !discovered_.load() || cycle_.running) return;
  const auto now = SteadyClock::now();
  const PollCyclePlan plan = scheduler_.plan_cycle(now);
  if (plan.empty()) {
    // Nobody to poll and no probe due yet: wake up for the next probe.
    if (const auto due = scheduler_.next_probe_due()) schedule_poll(std::max(*due, now + settings_.poll_period));
    return;
  }
  cycle_ = Cycle{true, now, 0};
  for (const auto& sync : plan.sync_reads) {
    ++cycle_.outstanding;
    enqueue_internal(sync_read_job(sync.block, sync.ids));
  }
  for (const auto id : plan.reads) enqueue_poll_read(id, false);
  for (const auto id : plan.probes) enqueue_poll_read(id, true);
}

void PacketBusEngine::Impl::enqueue_poll_read(std::uint8_t servo_id, bool probe) {
  const PollTarget* target = scheduler_.target(servo_id);
  if (target == nullptr) return;
  // A probe is one attempt: an offline servo costs at most one timeout per probe period.
  Job job = read_job(servo_id, target->block, probe ? 1 : 1 + settings_.retries);
  job.done = [this, servo_id, probe](BusResult result) { on_poll_read(servo_id, probe, result); };
  ++cycle_.outstanding;
  enqueue_internal(std::move(job));
}

void PacketBusEngine::Impl::on_poll_read(std::uint8_t servo_id, bool probe, const BusResult& result) {
  switch (result.status) {
    case BusStatus::Ok:
      cache_.store_block(servo_id, result.data, SteadyClock::now());
      servo_answered(servo_id);
      break;
    case BusStatus::ServoRefused:
      servo_answered(servo_id);
      if (!poll_refusal_logged_.test(servo_id)) {
        poll_refusal_logged_.set(servo_id);
        spdlog::warn("{} — check the poll fields configured for its table", result.detail);
      }
      break;
    case BusStatus::Timeout:
    case BusStatus::Corrupt:
      servo_silent(servo_id, probe ? "probe unanswered" : result.detail, true);
      break;
    default:
      break;
  }
  poll_job_done();
}

void PacketBusEngine::Impl::on_sync_read_finished(const Active& active) {
  // Whoever stayed silent in the SYNC READ is read on its own, with retries, in this cycle:
  // only a failed READ takes a servo offline.
  for (const auto id : active.job.sync_ids) {
    if (active.sync_answered.test(id)) continue;
    note_timeout(id);
    enqueue_poll_read(id, false);
  }
  poll_job_done();
}

void PacketBusEngine::Impl::poll_job_done() {
  if (!cycle_.running || --cycle_.outstanding > 0) return;
  const auto now = SteadyClock::now();
  cycle_.running = false;
  counters_.poll_cycles.fetch_add(1, std::memory_order_relaxed);
  counters_.last_poll_cycle_us.store(saturate_us(now - cycle_.started), std::memory_order_relaxed);
  const bool anyone_online = std::any_of(scheduler_.targets().begin(), scheduler_.targets().end(),
                                         [this](const PollTarget& target) {
                                           return scheduler_.presence(target.servo_id) != Presence::Offline;
                                         });
  if (anyone_online) return schedule_poll(cycle_.started + settings_.poll_period);
  if (const auto due = scheduler_.next_probe_due()) schedule_poll(*due);
}

void PacketBusEngine::Impl::servo_answered(std::uint8_t servo_id) {
  const PresenceChange change = scheduler_.answered(servo_id);
  cache_.set_online(servo_id, true);
  if (change != PresenceChange::CameOnline) return;
  spdlog::info("bus {}: servo {} answers again: online", settings_.name, servo_id);
  if (!identity_known_.test(servo_id)) read_identity(servo_id, std::nullopt);
}

void PacketBusEngine::Impl::servo_silent(std::uint8_t servo_id, const std::string& reason, bool log) {
  const PresenceChange change = scheduler_.silent(servo_id, SteadyClock::now());
  cache_.set_online(servo_id, false);
  if (log && change == PresenceChange::WentOffline) {
    spdlog::warn("bus {}: servo {} offline ({}); probing it every {} ms", settings_.name, servo_id, reason,
                 settings_.probe_period.count());
  }
}

// ==== public face ===========================================================================

PacketBusEngine::PacketBusEngine(BusSettings settings) : impl_(std::make_unique<Impl>(std::move(settings))) {}
PacketBusEngine::~PacketBusEngine() = default;
void PacketBusEngine::start() { impl_->start(); }
void PacketBusEngine::stop() { impl_->stop(); }
void PacketBusEngine::submit(BusOp op, Priority priority, Completion done) {
  impl_->submit(std::move(op), priority, std::move(done));
}
const BusSettings& PacketBusEngine::settings() const { return impl_->settings(); }
bool PacketBusEngine::bus_up() const { return impl_->bus_up(); }
BusCountersSnapshot PacketBusEngine::counters() const { return impl_->counters(); }
const PollCache& PacketBusEngine::cache() const { return impl_->cache(); }
bool PacketBusEngine::discovered() const { return impl_->discovered(); }

}  // namespace sms::gateway
