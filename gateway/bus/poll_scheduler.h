#pragma once
// The cyclic-polling plan of one bus (docs/PLC_GUIDE.md "A silent servo must not stall
// the bus"): which frames a poll cycle sends, and when a silent servo is probed. Pure logic,
// no I/O and no clock of its own; the bus engine runs it on the bus thread and feeds back
// what happened.
//
// - Online servos whose table has SYNC READ and that poll the same block share one SYNC READ
//   frame per cycle; other online servos get one READ each.
// - A servo whose poll READ stays unanswered through every retry goes offline. It then leaves
//   the SYNC READ list (so it cannot make every cycle wait for it) and gets one single-attempt
//   probe READ per probe period; the first answer brings it back.
#include <chrono>
#include <cstdint>
#include <optional>
#include <vector>

#include "gateway/bus/poll_cache.h"

namespace sms::gateway {

struct PollTarget {
  std::uint8_t servo_id = 0;
  AddressBlock block;      // the feedback block to poll
  bool sync_read = false;  // its table has SYNC READ (modbus_map TableSpec::has_sync_read)
};

struct PollCyclePlan {
  struct SyncRead {
    AddressBlock block;
    std::vector<std::uint8_t> ids;  // in configuration order; replies come back in this order
  };
  std::vector<SyncRead> sync_reads;
  std::vector<std::uint8_t> reads;   // online servos read one by one (with retries)
  std::vector<std::uint8_t> probes;  // offline servos whose probe is due (one attempt)

  bool empty() const { return sync_reads.empty() && reads.empty() && probes.empty(); }
};

enum class Presence : std::uint8_t { Unknown, Online, Offline };
enum class PresenceChange : std::uint8_t { None, CameOnline, WentOffline };

class PollScheduler {
 public:
  PollScheduler(std::vector<PollTarget> targets, std::chrono::milliseconds probe_period);

  // `polls`: the online servos' reads too; without, only the probes that are due.
  PollCyclePlan plan_cycle(SteadyClock::time_point now, bool polls = true) const;
  // The servo answered (any poll, probe or discovery transaction).
  PresenceChange answered(std::uint8_t servo_id);
  // A poll READ failed through every retry, a probe failed, or discovery's PING did: offline,
  // next probe one probe period from `now` (or `next_probe_in`, shorter, for a servo that may
  // only have been held up: the engine's backoff for servos offline for answering late).
  PresenceChange silent(std::uint8_t servo_id, SteadyClock::time_point now,
                        std::optional<std::chrono::milliseconds> next_probe_in = std::nullopt);
  // The bus went down: nobody is known to answer; when it is back everybody is probed at once.
  void forget_all();

  Presence presence(std::uint8_t servo_id) const;
  const PollTarget* target(std::uint8_t servo_id) const;
  const std::vector<PollTarget>& targets() const { return targets_; }
  // Earliest time an offline servo is due for its probe; nullopt when none is offline.
  std::optional<SteadyClock::time_point> next_probe_due() const;
  std::chrono::milliseconds probe_period() const { return probe_period_; }

 private:
  struct State {
    Presence presence = Presence::Unknown;
    SteadyClock::time_point next_probe{};
  };
  std::vector<PollTarget> targets_;
  std::vector<State> states_;  // parallel to targets_
  std::chrono::milliseconds probe_period_;
  std::optional<std::size_t> index_of(std::uint8_t servo_id) const;
};

}  // namespace sms::gateway
