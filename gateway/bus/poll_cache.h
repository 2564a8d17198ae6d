#pragma once
// What the gateway knows about each servo of one bus without asking it: the feedback block
// as last polled (raw bus bytes from its base address), when it was polled, whether the servo
// answers, its last status byte, its identity from discovery and its counters. The bus thread
// writes; Modbus TCP threads read (input registers 04 and 1000-1008, docs/PLC_GUIDE.md) — so a
// read of the input registers never touches the bus.
//
// The servo set is fixed at construction; reads take one mutex per bus for the few
// microseconds of a copy and never allocate. Addresses are bus addresses: bytes on packet
// buses (one byte each), registers on modbus-rtu buses (two bytes each, high byte first, as
// on the wire) — `bytes_per_address` at construction.
#include <array>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <vector>

#include "gateway/bus/bus_counters.h"
#include "protocol/packet.h"

namespace sms::gateway {

using SteadyClock = std::chrono::steady_clock;

// A contiguous run of bus addresses: bytes on packet buses, registers on modbus-rtu buses.
struct AddressBlock {
  std::uint16_t address = 0;
  std::uint16_t count = 0;
  std::uint16_t end() const { return static_cast<std::uint16_t>(address + count); }
  bool contains(std::uint16_t first, std::size_t n) const { return first >= address && first + n <= end(); }
  friend bool operator==(const AddressBlock&, const AddressBlock&) = default;
};

// What discovery read from the servo (discovery.h says which addresses, per table).
struct ServoIdentity {
  std::optional<std::uint16_t> model;     // sts: model major << 8 | minor; d55d: vendor code
  std::optional<std::uint16_t> firmware;  // sts: firmware major << 8 | minor; sms1, d55d: software version
  friend bool operator==(const ServoIdentity&, const ServoIdentity&) = default;
};

// Everything about one servo except its bytes, copied out under the lock.
struct CachedServoState {
  std::uint8_t servo_id = 0;
  AddressBlock block;
  bool online = false;  // answered its last poll or probe
  OfflineReason offline_reason = OfflineReason::None;
  bool has_data = false;            // the block was read at least once
  SteadyClock::time_point updated;  // when the block was last read (meaningless without has_data)
  ServoIdentity identity;
  // The servo's response-level field (sts/sms1 address 8, d55d 16) as read at discovery and
  // kept current when a client WRITE or SYNC WRITE through this gateway changes it: whether
  // the servo answers writes. Empty until read.
  std::optional<std::uint8_t> response_level;
  ServoCountersSnapshot counters;  // replies OK, timeouts, last status byte

  // Age of the data at `now`; nullopt before the first read.
  std::optional<SteadyClock::duration> age(SteadyClock::time_point now) const {
    if (!has_data) return std::nullopt;
    return now - updated;
  }
};

enum class CacheRead : std::uint8_t {
  Ok,
  UnknownServo,  // not configured on this bus
  OutsideBlock,  // the range is not (entirely) inside the polled block
  NoData,        // not polled successfully yet (servo offline since start)
};

class PollCache {
 public:
  struct ServoEntry {
    std::uint8_t servo_id = 0;
    AddressBlock block;
  };
  // Servo IDs must be unique and below the broadcast ID; `bytes_per_address` is 1 or 2.
  // Throws std::invalid_argument.
  explicit PollCache(std::span<const ServoEntry> servos, std::uint8_t bytes_per_address = 1);
  PollCache(const PollCache&) = delete;
  PollCache& operator=(const PollCache&) = delete;

  // --- readers (any thread) ----------------------------------------------------------------
  bool contains(std::uint8_t servo_id) const { return index_[servo_id] != kNoServo; }
  std::vector<std::uint8_t> servo_ids() const;
  std::optional<AddressBlock> block(std::uint8_t servo_id) const;
  std::uint8_t bytes_per_address() const { return bytes_per_address_; }
  // Copies the bytes of addresses [address, address + out.size() / bytes_per_address()) of the
  // last polled block into `out`, and the servo's state into `*state` when given (also on
  // NoData, for online/age/counters). An `out` that is not a whole number of addresses is
  // OutsideBlock.
  CacheRead copy(std::uint8_t servo_id, std::uint16_t address, std::span<std::uint8_t> out,
                 CachedServoState* state = nullptr) const;
  std::optional<CachedServoState> state(std::uint8_t servo_id) const;
  std::size_t online_count() const;
  std::size_t offline_count(OfflineReason reason) const;  // offline servos of that reason

  // --- writer (the bus thread) -------------------------------------------------------------
  // Stores a freshly read block (exactly block.count x bytes_per_address bytes; anything else
  // is ignored) and marks the servo online.
  void store_block(std::uint8_t servo_id, std::span<const std::uint8_t> bytes, SteadyClock::time_point when);
  void set_online(std::uint8_t servo_id, bool online);  // false: set_offline(NoAnswer)
  // Offline for `reason`; a servo offline for answering late stays so until it answers (a probe
  // that goes unanswered does not make it "no answer"). Returns the reason it had before.
  OfflineReason set_offline(std::uint8_t servo_id, OfflineReason reason);
  void set_all_offline();
  void set_identity(std::uint8_t servo_id, const ServoIdentity& identity);
  void set_response_level(std::uint8_t servo_id, std::optional<std::uint8_t> level);
  // Counters are atomics outside the lock: the bus thread bumps them on every answer.
  ServoCounters* counters(std::uint8_t servo_id);
  const ServoCounters* counters(std::uint8_t servo_id) const;

 private:
  static constexpr std::uint8_t kNoServo = 0xFF;
  struct Slot {
    std::uint8_t servo_id = 0;
    AddressBlock block;
    protocol::Bytes bytes;  // block.count x bytes_per_address, allocated once
    bool online = false;
    OfflineReason offline_reason = OfflineReason::None;
    bool has_data = false;
    SteadyClock::time_point updated;
    ServoIdentity identity;
    std::optional<std::uint8_t> response_level;
  };
  const Slot* slot(std::uint8_t servo_id) const;
  Slot* slot(std::uint8_t servo_id);
  void fill_state(const Slot& slot, std::size_t index, CachedServoState& state) const;

  mutable std::mutex mutex_;
  std::uint8_t bytes_per_address_;
  std::vector<Slot> slots_;
  std::unique_ptr<ServoCounters[]> counters_;  // atomics cannot live in a resizable vector
  std::array<std::uint8_t, 256> index_{};      // servo ID -> slot, kNoServo when not configured
};

}  // namespace sms::gateway
