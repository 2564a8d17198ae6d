#pragma once
// The job queue every bus engine runs from: one FIFO per Priority, taken in next_level() order
// (bus_engine.h), client jobs counted against the bus's queue depth, the engine's own jobs
// (poll, probe, discovery) not. Not thread-safe: the engine holds its lock around each call.
//
// `Job` needs `bool client`, `MotionEpoch motion_epoch`, `SteadyClock::time_point queued_at` and
// `Completion done`.
#include <array>
#include <chrono>
#include <cstddef>
#include <deque>
#include <mutex>
#include <optional>
#include <vector>

#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_engine.h"

namespace sms::gateway {

template <typename Job>
class JobQueue {
 public:
  // Queues a client job at `priority` unless admission() (bus_engine.h) refuses it; Ok when queued.
  BusStatus admit(Job& job, Priority priority, bool accepting, bool bus_up, std::size_t depth) {
    const BusStatus refusal = admission(accepting, bus_up, clients_, depth, priority);
    if (refusal != BusStatus::Ok) return refusal;
    job.client = true;
    job.queued_at = SteadyClock::now();
    level(priority).push_back(std::move(job));
    ++clients_;
    return BusStatus::Ok;
  }
  // The engine's own work: never refused, not counted against the depth.
  void push_internal(Job job, Priority priority) {
    job.client = false;
    job.queued_at = SteadyClock::now();
    level(priority).push_back(std::move(job));
  }
  // A job taken with pop() goes back to the front of `priority` (a stop came in between).
  void push_front(Job job, Priority priority) {
    if (job.client) ++clients_;
    level(priority).push_front(std::move(job));
  }

  // The level to take next (next_level(), bus_engine.h), or nullopt when empty.
  std::optional<std::size_t> next(const std::array<std::chrono::nanoseconds, kPriorityCount>& age_limits,
                                   SteadyClock::time_point now) const {
    return next_level(levels_, age_limits, now);
  }
  bool empty(Priority priority) const { return levels_[static_cast<std::size_t>(priority)].empty(); }
  const Job& front(std::size_t level_index) const { return levels_.at(level_index).front(); }
  Job pop(std::size_t level_index) {
    auto& queue = levels_.at(level_index);
    Job job = std::move(queue.front());
    queue.pop_front();
    if (job.client) --clients_;
    return job;
  }
  // Empties the queue: the client jobs come back (they must be answered); the engine's own are
  // dropped (rebuilt when the bus is back).
  std::vector<Job> take_clients() {
    std::vector<Job> clients;
    for (auto& queue : levels_) {
      for (auto& job : queue) {
        if (job.client) clients.push_back(std::move(job));
      }
      queue.clear();
    }
    clients_ = 0;
    return clients;
  }

 private:
  std::deque<Job>& level(Priority priority) { return levels_[static_cast<std::size_t>(priority)]; }

  std::array<std::deque<Job>, kPriorityCount> levels_;
  std::size_t clients_ = 0;
};

// submit() on every bus once its job is made: queued under `mutex` (true: wake the bus thread),
// or the refusal answered at once on the caller's thread (QueueFull counted).
template <typename Job>
bool queue_client_job(const BusSettings& settings, BusCounters& counters, std::mutex& mutex, JobQueue<Job>& queue,
                      Job job, Priority priority, const bool& accepting, bool bus_up) {
  BusStatus refusal = BusStatus::Ok;
  {
    std::lock_guard lock(mutex);
    refusal = queue.admit(job, priority, accepting, bus_up, settings.queue_depth);
  }
  if (refusal == BusStatus::Ok) return true;
  if (refusal == BusStatus::QueueFull) counters.queue_full.fetch_add(1, std::memory_order_relaxed);
  complete(settings, job.done, BusResult{refusal, 0, {}, refusal_detail(refusal, settings)});
  return false;
}

}  // namespace sms::gateway
