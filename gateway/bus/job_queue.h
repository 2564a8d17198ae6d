#pragma once
// The queue every bus engine runs from, and the one home of its rules (docs/DECISIONS.md
// "Gateway", Priorities):
// - admission (submit()): a client operation is taken while the engine runs (else Cancelled) and
//   its line is up (else BusDown), up to the bus's queue depth over every priority (else QueueFull
//   -> 0x06); a safe stop is never QueueFull (a full queue must not keep a motor from stopping).
//   A refusal is answered at once, on the caller's thread, before submit() returns;
// - the picking rule (take()):
//   1. safe stops (Priority::Safety), always first;
//   2. else the job that has waited longest among those past their level's age limit: no kind of
//      work waits without bound behind another — a live read behind a flood of writes, a poll
//      behind a flood of live reads;
//   3. else strict priority, FIFO within a priority (a connection's writes keep their order);
// - the age limits: client work may wait kClientAgeLimit behind higher-priority client work, the
//   engine's own work (poll, probe, discovery) one poll period (at least 10 ms);
// - its lock: every member may be called from any thread (submitting threads, the bus thread).
//
// `Job` needs `bool client`, `SteadyClock::time_point queued_at` and `Completion done`.
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cstddef>
#include <deque>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_engine.h"

namespace sms::gateway {

template <typename Job>
class JobQueue {
 public:
  // How long a client operation may wait behind higher-priority client work before it goes next
  // (rule 2): a few transactions at 1 Mbit/s, one at slow rates.
  static constexpr std::chrono::milliseconds kClientAgeLimit{2};

  // `settings` (name, device, queue depth, poll period) and `counters` (QueueFull) outlive the queue.
  JobQueue(const BusSettings& settings, BusCounters& counters)
      : settings_(settings),
        counters_(counters),
        age_limits_{std::chrono::nanoseconds{0}, kClientAgeLimit, kClientAgeLimit,
                    std::max<std::chrono::nanoseconds>(settings.poll_period, std::chrono::milliseconds{10})} {}
  JobQueue(const JobQueue&) = delete;
  JobQueue& operator=(const JobQueue&) = delete;

  // --- the engine's life -------------------------------------------------------------------------
  // start(): client work is taken from now on; false when it already was.
  bool open() {
    std::lock_guard lock(mutex_);
    if (accepting_) return false;
    accepting_ = true;
    return true;
  }
  // stop(): client work is refused (Cancelled) from now on, and the bus thread is to finish.
  void close() {
    std::lock_guard lock(mutex_);
    accepting_ = false;
    closing_ = true;
  }
  bool closing() const {
    std::lock_guard lock(mutex_);
    return closing_;
  }
  // The port opened: client work is taken.
  void line_up() {
    std::lock_guard lock(mutex_);
    line_up_.store(true);
    down_reason_.clear();
  }
  // The port was lost or closed: client work is refused (BusDown) from now on, with `why` when
  // given (else "serial port ... is not open"). Empties the queue in the same step: the client
  // jobs come back (they must be answered), the engine's own are dropped (rebuilt when the bus is back).
  std::vector<Job> line_down(std::string why = {}) {
    std::vector<Job> clients;
    std::lock_guard lock(mutex_);
    line_up_.store(false);
    down_reason_ = std::move(why);
    for (auto& level : levels_) {
      for (auto& job : level) {
        if (job.client) clients.push_back(std::move(job));
      }
      level.clear();
    }
    clients_ = 0;
    return clients;
  }
  // Lock-free (the engine's bus_up()).
  bool line_is_up() const { return line_up_.load(); }

  // --- submitting threads ------------------------------------------------------------------------
  // A client job: queued (true: wake the bus thread), or its refusal answered now (false).
  bool submit(Job job, Priority priority) {
    BusStatus refusal = BusStatus::Ok;
    std::string down_reason;
    {
      std::lock_guard lock(mutex_);
      if (!accepting_) {
        refusal = BusStatus::Cancelled;
      } else if (!line_up_.load()) {
        refusal = BusStatus::BusDown;
        down_reason = down_reason_;
      } else if (clients_ >= settings_.queue_depth && priority != Priority::Safety) {
        refusal = BusStatus::QueueFull;
      } else {
        job.client = true;
        job.queued_at = SteadyClock::now();
        levels_[static_cast<std::size_t>(priority)].push_back(std::move(job));
        ++clients_;
        return true;
      }
    }
    if (refusal == BusStatus::QueueFull) counters_.queue_full.fetch_add(1, std::memory_order_relaxed);
    complete(job, BusResult{refusal, 0, {}, refusal_detail(refusal, down_reason)});
    return false;
  }

  // --- the bus thread ----------------------------------------------------------------------------
  // The engine's own work (poll, probe, discovery): at Priority::Poll, never refused, not counted
  // against the depth.
  void push_internal(Job job) {
    job.client = false;
    job.queued_at = SteadyClock::now();
    std::lock_guard lock(mutex_);
    levels_[static_cast<std::size_t>(Priority::Poll)].push_back(std::move(job));
  }
  // The job to run at `now` by the picking rule, or nullopt when nothing is queued.
  std::optional<Job> take(SteadyClock::time_point now) {
    std::lock_guard lock(mutex_);
    const auto level = next_level(now);
    if (!level) return std::nullopt;
    auto& queue = levels_[*level];
    Job job = std::move(queue.front());
    queue.pop_front();
    if (job.client) --clients_;
    return job;
  }

  // Runs `job.done` (if set) with `result`; a handler that throws is logged, never let loose on
  // the bus thread. Every job of the engine is answered through here.
  void complete(Job& job, BusResult result) const {
    if (!job.done) return;
    try {
      job.done(std::move(result));
    } catch (const std::exception& error) {
      spdlog::error("bus {}: a completion handler threw: {}", settings_.name, error.what());
    }
  }

 private:
  // The picking rule (the header comment's 1-3) over the levels; call with mutex_ held.
  std::optional<std::size_t> next_level(SteadyClock::time_point now) const {
    constexpr auto kSafety = static_cast<std::size_t>(Priority::Safety);
    if (!levels_[kSafety].empty()) return kSafety;
    std::optional<std::size_t> overdue;
    for (std::size_t level = kSafety + 1; level < kPriorityCount; ++level) {
      if (levels_[level].empty() || now - levels_[level].front().queued_at < age_limits_[level]) continue;
      if (!overdue || levels_[level].front().queued_at < levels_[*overdue].front().queued_at) overdue = level;
    }
    if (overdue) return overdue;
    for (std::size_t level = 0; level < kPriorityCount; ++level) {
      if (!levels_[level].empty()) return level;
    }
    return std::nullopt;
  }

  // A refusal's text for logs and answers: "bus arm: 64 operations already queued".
  std::string refusal_detail(BusStatus refusal, const std::string& down_reason) const {
    const std::string bus = "bus " + settings_.name + ": ";
    switch (refusal) {
      case BusStatus::Cancelled: return bus + "the bus engine is not running";
      case BusStatus::BusDown:
        if (!down_reason.empty()) return bus + down_reason;
        return bus + "serial port " + settings_.serial.device + " is not open (bus down)";
      case BusStatus::QueueFull: return bus + std::to_string(settings_.queue_depth) + " operations already queued";
      default: return bus + std::string(to_string(refusal));
    }
  }

  const BusSettings& settings_;
  BusCounters& counters_;
  // Per Priority: how long a job may wait before it goes ahead of higher priorities (rule 2).
  const std::array<std::chrono::nanoseconds, kPriorityCount> age_limits_;

  mutable std::mutex mutex_;
  std::array<std::deque<Job>, kPriorityCount> levels_;  // one FIFO per Priority
  std::size_t clients_ = 0;                             // client jobs queued, every priority
  bool accepting_ = false;
  bool closing_ = false;
  std::atomic<bool> line_up_{false};  // written under mutex_ (with the queue), read without it too
  std::string down_reason_;           // guarded by mutex_; empty: the port is simply not open
};

}  // namespace sms::gateway
