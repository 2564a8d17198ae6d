#pragma once
// The narrow, per-protocol part of a bus: one transaction at a time, synchronously, on the
// calling thread — the bus engine's thread (engine_core.h) or an integrator tool's main thread
// (gateway/tools/tool_link.cpp). Two transactors exist:
//   PacketTransactor (packet_transactor.h): feetech `FF FF` and d55d `D5 5D` packets through
//                     SerialPort and the stream decoder;
//   RtuTransactor    (rtu_transactor.h):    Modbus RTU through libmodbus (RtuMaster).
// Each has the same face, which the engine core is written against (a template parameter, so
// each protocol keeps its own request type); the BusTransactor concept at the end of this file
// is that face as the compiler checks it:
//
//   using Request = ...;                        // one encoded transaction with its attempts
//   Expected<Ok> open(); void close(); bool is_open() const;
//   std::string line_description() const;       // "feetech at 1000000 bit/s, none parity, 1 stop bit"
//   std::string_view protocol_name() const;      // for the discovery summary
//   Request prepare(BusOp&& op, unsigned attempts) const;   // throws std::invalid_argument
//   Request read_request(servo, AddressBlock, attempts) const;
//   Request ping_request(servo, attempts) const;           // "is anything there?"
//   Request sync_read_request(AddressBlock, ids) const;    // packet feetech only (has_sync_read)
//   static std::uint8_t target(const Request&);            // the addressed servo
//   static bool broadcast(const Request&);                 // nothing answers by address
//   BusResult execute(const Request&, TransactionEvents&); // retries inside; BusDown = port lost
//   std::uint8_t refusal_bits() const;           // status bits that speak of the instruction only
//   std::optional<std::uint8_t> status_in_block(const AddressBlock&, span data) const;
//   void for_each_write(const Request&, fn(servo, address, span data)) const;
//   static std::string check_servo(const ServoSettings&);  // why the bus cannot poll it; empty: it can
//   static constexpr std::size_t kBytesPerAddress;         // 1 (packet tables) or 2 (registers)
//   static constexpr bool kAnswersCarryStatus;             // every answer has a status byte
//   bool has_sync_read() const; static bool broadcast_id(std::uint8_t);
//
// Late answers (docs/DECISIONS.md "Late answers"): an answer names no request, so one that
// comes after its request gave up is indistinguishable from the answer to the next request of
// the same size to the same servo. Each transactor therefore (1) reads and drops what the input holds before
// every request (counted as stray bytes), and (2) remembers, per servo, how many of its requests
// went unanswered (OwedAnswers below): before the next request to that servo it watches the line,
// dropping everything, until those answers have come or the late-answer window has passed since
// the last unanswered request. Requests to other servos are not held up: a late answer from
// another address is never taken for theirs.
//
// Bus-wide counters (frames, timeouts, checksum errors, stray frames, retries, discarded bytes)
// are counted by the transactor into the BusCounters it is given; what concerns one servo is
// reported through TransactionEvents, so the engine keeps its per-servo counters, status byte
// and presence, and a tool learns what it heard.
#include <algorithm>
#include <array>
#include <chrono>
#include <concepts>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include <spdlog/spdlog.h>

#include "config/config.h"
#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_engine.h"

namespace sms::gateway {

class TransactionEvents {
 public:
  virtual ~TransactionEvents() = default;
  // A valid answer from `servo_id`; `status` is its status/ERROR byte where the answer carries
  // one (packet protocols), as it came (refusal bits included).
  virtual void answered(std::uint8_t /*servo_id*/, std::optional<std::uint8_t> /*status*/) {}
  // An attempt addressed to `servo_id` ended without a valid answer in time.
  virtual void unanswered(std::uint8_t /*servo_id*/) {}
  // One member's answer to a SYNC READ (its data, `count` bytes).
  virtual void sync_answer(std::uint8_t /*servo_id*/, std::span<const std::uint8_t> /*data*/) {}
  // A valid frame that was not the answer, from `id` (a late answer, another servo).
  virtual void foreign(std::uint8_t /*id*/) {}
  // Bytes that made no valid frame (damaged answers, colliding answers, noise).
  virtual void damaged() {}
};

// What each transactor needs of the line beyond the serial settings: how long a servo may take
// to start answering after the request has left the wire (its return delay plus the adapter's
// latency) and a prefix for messages ("bus arm: "; empty for the tools).
struct TransactionTiming {
  std::chrono::nanoseconds reply_allowance{std::chrono::milliseconds{20}};
  std::string label;
};

// How long after an unanswered request its answer may still come, in attempt timeouts (each the
// request's and the answer's wire time plus the reply allowance): an answer later than this is
// not guarded against (it is then a servo or adapter fault far outside its configured timing).
inline constexpr unsigned kLateAnswerWindowAttempts = config::kLateAnswerWindowAttempts;  // one home: config.h

// Answers still owed by servos whose requests went unanswered, and until when they may come.
class OwedAnswers {
 public:
  using Clock = std::chrono::steady_clock;

  // `count` more requests to `id` went unanswered; their answers may come until `until`.
  void add(std::uint8_t id, unsigned count, Clock::time_point until) {
    if (count == 0) return;
    Entry& entry = entries_[id];
    if (entry.until <= Clock::now()) entry.count = 0;  // what was owed before has expired
    entry.count += count;
    entry.until = std::max(entry.until, until);
  }
  // A frame from `id` came that was not taken as an answer: one owed answer fewer.
  void arrived(std::uint8_t id) {
    Entry& entry = entries_[id];
    if (entry.count > 0) --entry.count;
  }
  // Whether answers of `id` may still come at `now`.
  bool owes(std::uint8_t id, Clock::time_point now) const {
    const Entry& entry = entries_[id];
    return entry.count > 0 && now < entry.until;
  }
  unsigned count(std::uint8_t id) const { return entries_[id].count; }
  Clock::time_point until(std::uint8_t id) const { return entries_[id].until; }
  // Nothing can still come from anyone (a reopened line).
  void clear() { entries_ = {}; }

  // The attempts of one transaction to `id`: however it ends, the answers of those not heard are
  // owed until `window` after the last one was sent. (A late answer to an earlier attempt of the
  // same request is that request's answer all the same: only later requests need the wait.)
  class Tally {
   public:
    Tally(OwedAnswers& owed, std::uint8_t id, std::chrono::nanoseconds window, bool awaited)
        : owed_(owed), id_(id), window_(window), awaited_(awaited) {}
    ~Tally() {
      if (awaited_ && sent_ > heard_) owed_.add(id_, sent_ - heard_, last_sent_ + window_);
    }
    Tally(const Tally&) = delete;
    Tally& operator=(const Tally&) = delete;
    void sent(Clock::time_point at) {
      ++sent_;
      last_sent_ = at;
    }
    void heard() { ++heard_; }  // an answer (valid or damaged) from `id` to one of the attempts
    Clock::time_point last_sent() const { return last_sent_; }

   private:
    OwedAnswers& owed_;
    std::uint8_t id_;
    std::chrono::nanoseconds window_;
    bool awaited_;
    unsigned sent_ = 0;
    unsigned heard_ = 0;
    Clock::time_point last_sent_{};
  };

 private:
  struct Entry {
    unsigned count = 0;
    Clock::time_point until{};
  };
  std::array<Entry, 256> entries_{};
};

// Counts bytes dropped unread as stray; the first time on a line it says so at info, then at debug.
class StrayBytes {
 public:
  explicit StrayBytes(BusCounters& counters) : counters_(counters) {}
  // `label`: the transaction timing's; `when()`: "before READ 56+15 of servo 1", built only
  // when something was dropped.
  template <typename When>
  void count(std::size_t bytes, const std::string& label, When&& when) {
    if (bytes == 0) return;
    counters_.stray_bytes.fetch_add(bytes, std::memory_order_relaxed);
    const auto level = told_ ? spdlog::level::debug : spdlog::level::info;
    if (!spdlog::should_log(level)) return;
    spdlog::log(level,
                "{}dropped {} byte{} {}: never taken for an answer (late answers to requests that gave up, noise; "
                "counted in sms_gateway_bus_stray_bytes_total{})",
                label, bytes, bytes == 1 ? "" : "s", when(), told_ ? "" : "; further ones logged at debug");
    told_ = true;
  }

 private:
  BusCounters& counters_;
  bool told_ = false;
};

// The transactor contract above, checked by the compiler: EngineCore and the tools' link take a
// BusTransactor, and bus_engine.cpp asserts that both transactors are one. Everything EngineCore
// asks of its transactor is listed here (a member it uses that is missing here is a bug here).
namespace transactor_contract {
struct WriteVisitor {
  void operator()(std::uint8_t, std::uint16_t, std::span<const std::uint8_t>) const {}
};
}  // namespace transactor_contract

template <class T>
concept BusTransactor = requires(T& transactor, const T& line, BusOp op, const typename T::Request& request,
                                 TransactionEvents& events, AddressBlock block, std::vector<std::uint8_t> ids,
                                 const ServoSettings& servo, std::span<const std::uint8_t> data, std::uint8_t id,
                                 unsigned attempts) {
  { transactor.open() } -> std::same_as<Expected<Ok>>;
  transactor.close();
  { line.is_open() } -> std::convertible_to<bool>;
  { line.line_description() } -> std::convertible_to<std::string>;
  { line.protocol_name() } -> std::convertible_to<std::string_view>;
  { line.prepare(std::move(op), attempts) } -> std::same_as<typename T::Request>;
  { line.read_request(id, block, attempts) } -> std::same_as<typename T::Request>;
  { line.ping_request(id, attempts) } -> std::same_as<typename T::Request>;
  { line.sync_read_request(block, ids) } -> std::same_as<typename T::Request>;
  { T::target(request) } -> std::convertible_to<std::uint8_t>;
  { T::broadcast(request) } -> std::convertible_to<bool>;
  { T::broadcast_id(id) } -> std::convertible_to<bool>;
  { line.has_sync_read() } -> std::convertible_to<bool>;
  { transactor.execute(request, events) } -> std::same_as<BusResult>;
  { line.refusal_bits() } -> std::convertible_to<std::uint8_t>;
  { line.status_in_block(block, data) } -> std::same_as<std::optional<std::uint8_t>>;
  line.for_each_write(request, transactor_contract::WriteVisitor{});
  { T::check_servo(servo) } -> std::convertible_to<std::string>;
  // Compile-time constants, not just members of the right type.
  typename std::integral_constant<std::size_t, T::kBytesPerAddress>;
  typename std::bool_constant<T::kAnswersCarryStatus>;
};

}  // namespace sms::gateway
