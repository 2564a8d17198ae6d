#pragma once
// The one bus engine, for every protocol: EngineCore<PacketTransactor> runs feetech and d55d
// buses, EngineCore<RtuTransactor> modbus-rtu buses (make_bus_engine, bus_engine.h, picks).
// The core owns everything that is the same on every bus:
// - the job queue (job_queue.h: admission, priorities, the age rule, its lock) and, just before
//   the wire, the safety rules' motion gate (motion_refusal) and the owed safe stops;
// - presence: online / offline / probe (poll_scheduler.h), the offline short-cut for clients;
// - poll cycles and their accounting, discovery (PING, then the identity READ) and its summary;
// - the status byte rule (one rule for every answer kind, logged once per change);
// - port loss and reopen.
// The transactor (transactor.h) does one transaction of its protocol, synchronously.
//
// Threading (decided on measurement, docs/DECISIONS.md "Threading model"): one thread per bus
// runs a plain loop — take the next job, run its transaction to the end (blocking in ppoll or
// libmodbus), complete it — and sleeps (wakeup.h) when there is nothing to do until a job is
// submitted or the next poll cycle is due. The poll cycle's jobs are queued at
// the first transaction boundary after it falls due, so they age like everything else.
// Completions run on the bus thread, except QueueFull, BusDown while the port is down, and
// Cancelled after stop(), which run inside submit() on the caller's thread.
#include <array>
#include <atomic>
#include <bitset>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "gateway/bus/discovery.h"
#include "gateway/bus/job_queue.h"
#include "gateway/bus/poll_scheduler.h"
#include "gateway/bus/transactor.h"
#include "gateway/bus/wakeup.h"

namespace sms::gateway {

template <BusTransactor Transactor>
class EngineCore final : public BusEngine {
 public:
  using TransactorFactory = std::function<std::unique_ptr<Transactor>(const BusSettings&, BusCounters&)>;

  // Throws std::invalid_argument for settings it cannot run (see make_bus_engine).
  EngineCore(BusSettings settings, const TransactorFactory& make_transactor);
  ~EngineCore() override;
  EngineCore(const EngineCore&) = delete;
  EngineCore& operator=(const EngineCore&) = delete;

  void start() override;
  void stop() override;
  void submit(BusOp op, Priority priority, Completion done) override;
  void owe_stop(OwedStop stop) override;
  std::size_t owed_stop_count() const override { return owed_count_.load(std::memory_order_acquire); }
  std::vector<OwedStop> owed_stops() const override;
  void on_owed_stops_changed(std::function<void()> changed) override;
  bool lend_line(std::string why, std::chrono::milliseconds bound) override;
  bool take_back_line() override;
  bool line_lent() const override;

  const BusSettings& settings() const override { return settings_; }
  bool bus_up() const override { return queue_.line_is_up(); }
  BusCountersSnapshot counters() const override { return counters_.snapshot(); }
  const PollCache& cache() const override { return cache_; }
  bool discovered() const override { return discovered_.load(); }

 private:
  using Request = typename Transactor::Request;
  struct Job {
    Request request;
    bool client = false;           // from submit(): holds a slot of the bounded queue, completes on every outcome
    bool poll_read = false;        // a poll cycle's READ of an online servo (not a probe)
    MotionEpoch motion_epoch = 0;  // motion_refusal() just before the job goes on the wire
    SteadyClock::time_point queued_at{};  // the age rule (job_queue.h)
    Completion done;
    // A safe stop's writes (Priority::Safety on packet buses): a servo holding a staged write
    // gets the same write staged too, so a later ACTION cannot run a move staged before the stop.
    std::vector<WriteOp> stop_writes;
    bool staged_write = false;                // REG WRITE: the servo holds it until ACTION
    bool action = false;                      // ACTION: runs (and so clears) every staged write
    std::vector<std::uint8_t> sync_read_ids;  // a client's SYNC READ: whose answers it collects
    std::uint16_t sync_read_count = 0;        // and how many bytes each
  };
  struct Owed {
    OwedStop stop;
    SteadyClock::time_point since{};
    SteadyClock::time_point due{};  // next attempt
    unsigned attempts = 0;
  };
  // What a transaction tells the core about single servos.
  class Events final : public TransactionEvents {
   public:
    explicit Events(EngineCore& core) : core_(core) {}
    void answered(std::uint8_t servo_id, std::optional<std::uint8_t> status) override;
    void answered_in_time(std::uint8_t servo_id) override;
    bool late(std::uint8_t servo_id, std::chrono::milliseconds after_asked) override;
    void unanswered(std::uint8_t servo_id) override;
    void sync_answer(std::uint8_t servo_id, std::span<const std::uint8_t> data) override;

   private:
    EngineCore& core_;
  };

  // --- thread and queue -----------------------------------------------------------------------
  void run_thread();
  void run_loop();
  std::optional<Job> next_job();
  void enqueue_internal(Job job);
  void run(Job job);
  void shutdown();
  // The refusal of a motion write that a trip or the e-stop overtook while it was queued
  // (MotionBlocked -> 0x04, with the reason); nullopt: it may go on the wire.
  std::optional<BusResult> motion_refusal(MotionEpoch admitted) const;
  // --- owed safe stops (owe_stop) ----------------------------------------------------------------
  void deliver_owed_stops();
  bool deliver(std::uint8_t servo_id, const Owed& owed);                // false: the port was lost
  std::optional<BusResult> owed_refusal(const Request& request) const;  // a motion write to an owed servo
  void make_owed_due(std::optional<std::uint8_t> servo_id);             // nullopt: all of them
  void owed_stops_changed();                                            // tells on_owed_stops_changed's listener
  void neutralise_staged(const Job& job);

  // --- port -------------------------------------------------------------------------------------
  bool try_open();
  void port_lost(const std::string& reason);
  // The port is closed: every servo offline, queued client work answered BusDown (`why`), the
  // engine's own work dropped and rebuilt when the line is back. `lent`: by lend_line().
  void close_line(const std::string& why, bool lent);
  // lend_line() on the bus thread: closes the port once, then sleeps until taken back or stopped.
  void hand_over_line();

  // --- discovery, presence, polling ----------------------------------------------------------------
  void begin_discovery();
  void on_discovery_ping(std::size_t index, const BusResult& result);
  void read_identity(std::uint8_t servo_id, std::optional<std::size_t> discovery_index);
  void discovery_step_done();
  bool poll_due(SteadyClock::time_point now) const;
  void start_poll_cycle_if_due();
  void schedule_next_cycle(SteadyClock::time_point now);
  void reschedule_for_probe();
  void skip_probes_of_owed(PollCyclePlan& plan, SteadyClock::time_point now);
  void enqueue_poll_read(std::uint8_t servo_id, bool probe);
  void on_poll_read(std::uint8_t servo_id, AddressBlock block, bool probe, const BusResult& result);
  void on_sync_read_finished(const std::vector<std::uint8_t>& ids);
  void poll_job_done();
  void servo_answered(std::uint8_t servo_id);
  void servo_silent(std::uint8_t servo_id, const std::string& reason, bool log);
  // An answer it owed came late (Events::late): true once it is offline for answering late.
  bool servo_late(std::uint8_t servo_id, std::chrono::milliseconds after_asked);
  std::chrono::milliseconds first_late_probe() const;
  std::chrono::milliseconds next_late_probe(std::uint8_t servo_id);
  void note_status(std::uint8_t servo_id, std::uint8_t status);
  void note_timeout(std::uint8_t servo_id);  // a SYNC READ member that stayed silent
  void note_written(const Request& request);
  BusResult execute(const Request& request);  // the transactor's, one transaction (servo_late counts per one)
  // d55d: every servo `job` addresses hears an instruction now; one that went longer than its
  // heartbeat without one may have stopped by itself, which is logged and counted.
  void note_instructions(const Job& job);
  const ServoSettings* servo(std::uint8_t servo_id) const;
  unsigned attempts() const { return 1 + settings_.retries; }

  const BusSettings settings_;
  BusCounters counters_;
  std::unique_ptr<Transactor> transactor_;
  PollCache cache_;
  PollScheduler scheduler_;  // bus thread only
  Events events_{*this};

  // Shared with submitting threads.
  JobQueue<Job> queue_{settings_, counters_};  // its own lock
  Wakeup wake_;
  mutable std::mutex owed_mutex_;
  std::map<std::uint8_t, Owed> owed_;       // guarded by owed_mutex_
  std::atomic<std::size_t> owed_count_{0};  // owed_.size(), set under owed_mutex_, read without it
  std::mutex owed_listener_mutex_;          // held while the listener runs: replacing it waits for that
  std::function<void()> owed_listener_;     // guarded by owed_listener_mutex_
  std::atomic<bool> discovered_{false};
  std::thread thread_;
  // lend_line(): asked for by the lender, carried out by the bus thread, which says so in lent_.
  mutable std::mutex lend_mutex_;
  std::condition_variable lend_changed_;
  std::optional<std::string> lend_wanted_;   // guarded by lend_mutex_: why; nullopt: not lent
  bool lent_ = false;                        // guarded by lend_mutex_: the port is closed for the lend
  std::atomic<bool> lend_requested_{false};  // lend_wanted_ is set (read by the bus thread without the lock)

  // Bus thread only (and start(), before the thread runs).
  struct Cycle {
    bool running = false;
    SteadyClock::time_point started{};
    std::size_t outstanding = 0;
    bool polls = true;  // false: probes only, between polls (schedule_next_cycle)
  } cycle_;
  std::optional<SteadyClock::time_point> next_cycle_;  // when the next poll cycle is due; none: not scheduled
  SteadyClock::time_point next_poll_{};                // when the online servos are polled next
  struct Discovery {
    std::vector<DiscoveredServo> servos;
    std::size_t pending = 0;
  } discovery_;
  std::bitset<256> identity_known_;
  std::bitset<256> poll_refusal_logged_;  // servos whose refused poll was logged, until a poll succeeds
  std::bitset<256> identity_refusal_logged_;
  std::bitset<256> sync_answered_;  // members that answered the SYNC READ under way
  // A client's SYNC READ under way collects its answers here instead of the poll cache.
  std::map<std::uint8_t, protocol::Bytes>* sync_collect_ = nullptr;
  std::bitset<256> staged_;  // servos holding a staged write (REG WRITE since the last ACTION)
  // Transactions with late answers per servo since it last answered a request in time
  // (servo_late), and the servos struck in the transaction under way (execute).
  std::array<std::uint8_t, 256> late_strikes_{};
  std::bitset<256> struck_;
  // When a servo offline for answering late is probed next (next_late_probe); 0: not backing off.
  std::array<std::chrono::milliseconds, 256> late_probe_in_{};
  // d55d: when each servo last heard an instruction (note_instructions); none since the line opened.
  std::array<std::optional<SteadyClock::time_point>, 256> last_instruction_{};
  std::bitset<256> heartbeat_gap_logged_;
  bool open_failure_logged_ = false;
  bool holding_lent_line_ = false;  // the port was closed for a lend that has not been taken back yet
};

}  // namespace sms::gateway
