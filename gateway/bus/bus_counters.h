#pragma once
// Counters of one bus and of each servo on it. The bus thread increments them; any thread
// reads them (TCP threads serve them on the gateway unit and the servo units' 1004-1007,
// docs/PLC_GUIDE.md). Relaxed atomics: each counter is exact, a set read together is not a
// snapshot of one instant, which is all a monitoring register needs.
#include <atomic>
#include <cstdint>

namespace sms::gateway {

struct BusCountersSnapshot {
  std::uint64_t frames_ok = 0;           // valid reply frames taken as an answer
  std::uint64_t timeouts = 0;            // expected replies that did not come (each attempt, each servo of a SYNC READ)
  std::uint64_t checksum_errors = 0;     // frames with a wrong checksum or an impossible LEN (framing)
  std::uint64_t stray_frames = 0;        // valid frames that were not the answer: late replies, echoes, other IDs
  std::uint64_t discarded_bytes = 0;     // bytes dropped while hunting for a header in an answer window
  std::uint64_t retries = 0;             // attempts after the first
  std::uint64_t transactions = 0;        // bus operations finished (any outcome but QueueFull)
  std::uint64_t queue_full = 0;          // submissions refused with QueueFull
  std::uint64_t bus_down_events = 0;     // times the port was lost or could not be reopened after loss
  std::uint64_t poll_cycles = 0;         // finished poll cycles
  std::uint32_t last_poll_cycle_us = 0;  // duration of the last finished poll cycle
  // Bytes that came when no answer was awaited (late answers to requests that gave up, noise
  // between transactions): read and dropped before a request.
  std::uint64_t stray_bytes = 0;
  // Fence reads sent before a request because its servo still owed late answers that could look
  // like the request's answer (transactor.h "Late answers").
  std::uint64_t fences = 0;
};

struct BusCounters {
  std::atomic<std::uint64_t> frames_ok{0};
  std::atomic<std::uint64_t> timeouts{0};
  std::atomic<std::uint64_t> checksum_errors{0};
  std::atomic<std::uint64_t> stray_frames{0};
  std::atomic<std::uint64_t> discarded_bytes{0};
  std::atomic<std::uint64_t> retries{0};
  std::atomic<std::uint64_t> transactions{0};
  std::atomic<std::uint64_t> queue_full{0};
  std::atomic<std::uint64_t> bus_down_events{0};
  std::atomic<std::uint64_t> poll_cycles{0};
  std::atomic<std::uint32_t> last_poll_cycle_us{0};
  std::atomic<std::uint64_t> stray_bytes{0};
  std::atomic<std::uint64_t> fences{0};

  BusCountersSnapshot snapshot() const {
    constexpr auto relaxed = std::memory_order_relaxed;
    return {frames_ok.load(relaxed),    timeouts.load(relaxed),           checksum_errors.load(relaxed),
            stray_frames.load(relaxed), discarded_bytes.load(relaxed),    retries.load(relaxed),
            transactions.load(relaxed), queue_full.load(relaxed),         bus_down_events.load(relaxed),
            poll_cycles.load(relaxed),  last_poll_cycle_us.load(relaxed), stray_bytes.load(relaxed),
            fences.load(relaxed)};
  }
};

// Why a servo is offline (input register 1008 of its unit, docs/PLC_GUIDE.md "A servo unit").
enum class OfflineReason : std::uint8_t {
  None = 0,         // online, or not polled yet
  NoAnswer = 1,     // its poll went unanswered through every retry (or the bus went down)
  AnswersLate = 2,  // its answers come after the response timeout, again and again: probe only
};

struct ServoCountersSnapshot {
  std::uint64_t replies_ok = 0;      // valid answers from this servo (polls, probes, client operations)
  std::uint64_t timeouts = 0;        // attempts addressed to it that got no valid answer in time
  std::uint8_t last_status = 0;      // ERROR / status byte of its latest answer, refusal bits removed
  std::uint64_t late_answers = 0;    // answers that came after their request had given up
  std::uint64_t heartbeat_gaps = 0;  // d55d: times it went longer than its heartbeat without an instruction
};

struct ServoCounters {
  std::atomic<std::uint64_t> replies_ok{0};
  std::atomic<std::uint64_t> timeouts{0};
  std::atomic<std::uint8_t> last_status{0};
  std::atomic<std::uint64_t> late_answers{0};
  std::atomic<std::uint64_t> heartbeat_gaps{0};

  ServoCountersSnapshot snapshot() const {
    constexpr auto relaxed = std::memory_order_relaxed;
    return {replies_ok.load(relaxed), timeouts.load(relaxed), last_status.load(relaxed), late_answers.load(relaxed),
            heartbeat_gaps.load(relaxed)};
  }
};

}  // namespace sms::gateway
