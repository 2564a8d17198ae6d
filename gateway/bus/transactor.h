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
//   void owe_answer(const Request&);             // its answer may come although nobody awaited it
//   std::uint8_t refusal_bits() const;           // status bits that speak of the instruction only
//   std::optional<std::uint8_t> status_in_block(const AddressBlock&, span data) const;
//   void for_each_write(const Request&, fn(servo, address, span data)) const;
//   static std::string check_servo(const ServoSettings&);  // why the bus cannot poll it; empty: it can
//   static constexpr std::size_t kBytesPerAddress;         // 1 (packet tables) or 2 (registers)
//   static constexpr bool kAnswersCarryStatus;             // every answer has a status byte
//   bool has_sync_read() const; static bool broadcast_id(std::uint8_t);
//
// Late answers (docs/DECISIONS.md "Late answers"): an answer names no request, so one that
// comes after its request gave up could be taken for the answer to a later request that looks
// the same. Each transactor therefore (1) reads and drops what the input holds before every
// request (counted as stray bytes), and (2) remembers, per servo, the shapes of the requests that
// went unanswered (OwedAnswers below). A request whose answer no owed answer can look like goes
// at once, and a frame of an owed shape is dropped and counted; one whose answer could look
// like an owed one is preceded by a fence, a short read no owed answer looks like. Nothing waits
// for late answers: a silent servo costs the bus its attempts and nothing more.
//
// Bus-wide counters (frames, timeouts, checksum errors, stray frames, retries, discarded bytes)
// are counted by the transactor into the BusCounters it is given; what concerns one servo is
// reported through TransactionEvents, so the engine keeps its per-servo counters, status byte
// and presence, and a tool learns what it heard.
#include <algorithm>
#include <array>
#include <bitset>
#include <chrono>
#include <concepts>
#include <cstdint>
#include <initializer_list>
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
  // A valid answer from `servo_id` to the first attempt of a request: it answers in time.
  virtual void answered_in_time(std::uint8_t /*servo_id*/) {}
  // A valid frame that was not the answer, from `id` (a late answer, another servo).
  virtual void foreign(std::uint8_t /*id*/) {}
  // An answer `servo_id` owed to a request that had given up came after all (OwedAnswers), at
  // least `after_asked` after that request was sent: the servo answers later than the response
  // timeout allows. True when the servo is not to be asked again now (the engine took it offline
  // for answering late, docs/DECISIONS.md "A servo that answers late"): a transaction to it ends
  // there instead of waiting for an answer that will be as late.
  virtual bool late(std::uint8_t /*servo_id*/, std::chrono::milliseconds /*after_asked*/) { return false; }
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

// What an answer looks like, as far as one answer can be told from another: its function (the
// Modbus function code on RTU, without the exception bit; 0 on packet buses, whose answers all
// look alike) and the lengths it may have (a packet answer's parameter count; an RTU answer's PDU
// length, kExceptionLength for an exception). A request's shape is every answer it would take.
struct AnswerShape {
  static constexpr std::size_t kExceptionLength = 255;  // no RTU PDU is that long

  std::uint8_t function = 0;
  std::bitset<256> lengths;

  static AnswerShape of(std::uint8_t function, std::initializer_list<std::size_t> lengths) {
    AnswerShape shape{function, {}};
    for (const auto length : lengths) shape.lengths.set(length);
    return shape;
  }
  // One answer as it came.
  static AnswerShape frame(std::uint8_t function, std::size_t length) { return of(function, {length}); }
  // Some answer could be taken for either.
  bool overlaps(const AnswerShape& other) const {
    return function == other.function && (lengths & other.lengths).any();
  }
  bool operator==(const AnswerShape&) const = default;
};

// The answers servos still owe to requests that gave up (docs/DECISIONS.md "Late answers"):
// per servo, the shapes of its unanswered requests and how many of each, in the order asked.
// Nothing expires: a late answer is known by its shape, however late it comes. A request whose
// answer could look like an owed one is not sent as it is: a fence goes first (fence_length()),
// a read whose answer no other owed answer can look like; a servo answers in the order it was
// asked, so once the fence is answered what was asked before it has come or never will
// (fence_answered()).
class OwedAnswers {
 public:
  // `count` requests to `id` that would take an answer of `shape` went unanswered; `fence_units`:
  // they were fences of that many units (0: not a fence). Kept in the order asked, except that
  // after the first owed fence the order no longer matters (a fence's answer settles only what
  // came before the first fence of its length): there an entry of the same kind takes the count,
  // so a silent servo's list stays a few entries long.
  // `waited_since`: when the latest of them was sent, awaited and given up on; nullopt for a
  // request sent blind (nobody waited for its answer: it cannot be late).
  void add(std::uint8_t id, const AnswerShape& shape, unsigned count, unsigned fence_units = 0,
           std::optional<SteadyClock::time_point> waited_since = SteadyClock::now()) {
    if (count == 0) return;
    auto& owed = entries_[id];
    const auto first_fence =
        std::find_if(owed.begin(), owed.end(), [](const Entry& entry) { return entry.fence_units != 0; });
    const auto same = [&](const Entry& entry) {
      return entry.shape == shape && entry.fence_units == fence_units &&
             entry.waited_since.has_value() == waited_since.has_value();
    };
    Entry* entry = nullptr;
    if (const auto found = std::find_if(first_fence, owed.end(), same); found != owed.end()) {
      entry = &*found;
    } else if (!owed.empty() && same(owed.back())) {
      entry = &owed.back();
    } else {
      entry = &owed.emplace_back(Entry{shape, 0, fence_units, waited_since});
    }
    entry->count += count;
    if (waited_since) entry->waited_since = std::max(*entry->waited_since, *waited_since);
  }
  // What a frame that was nobody's answer turned out to be (arrived()).
  struct Arrival {
    bool owed = false;  // one of the answers its servo owed
    // Owed to a request that waited for it and gave up: since when it waited (the latest such
    // request's sending); the answer is at least that late. nullopt: not owed, or sent blind.
    std::optional<SteadyClock::time_point> late_since;
    explicit operator bool() const { return owed; }
  };
  // Whether a late answer of `id` could be taken for an answer of `shape`.
  bool collides(std::uint8_t id, const AnswerShape& shape) const {
    return std::any_of(entries_[id].begin(), entries_[id].end(),
                       [&](const Entry& entry) { return entry.shape.overlaps(shape); });
  }
  // A frame of `shape` from `id` came that was not taken as an answer: whether it was one of the
  // answers `id` owed (the oldest it can be: answers come in the order asked), and whether late.
  Arrival arrived(std::uint8_t id, const AnswerShape& shape) {
    auto& owed = entries_[id];
    for (auto entry = owed.begin(); entry != owed.end(); ++entry) {
      if (!entry->shape.overlaps(shape)) continue;
      const Arrival arrival{true, entry->waited_since};
      if (--entry->count == 0) owed.erase(entry);
      return arrival;
    }
    return {};
  }
  // An answer came that only `id`'s latest request could give: whatever it owed before has come
  // or never will.
  void settled(std::uint8_t id) { entries_[id].clear(); }
  bool owes(std::uint8_t id) const { return !entries_[id].empty(); }
  unsigned count(std::uint8_t id) const {
    unsigned total = 0;
    for (const auto& entry : entries_[id]) total += entry.count;
    return total;
  }
  // The fence read's length (1..`longest` units) before `request` to `id`. Its answer,
  // `fence_shape(units)`, must look like no answer to `request` and like no owed answer but those
  // of earlier fences of the same length (whichever of them answers, what was asked before the
  // first of them has come: fence_answered()). Best is one after whose answer nothing owed can
  // look like `request`'s answer any more: a length nobody owes, or one whose first owed fence
  // comes after everything that could; else the one that settles the most, and another fence
  // follows. nullopt when no length will do.
  template <typename ShapeOf>
  std::optional<unsigned> fence_length(std::uint8_t id, ShapeOf&& fence_shape, const AnswerShape& request,
                                       unsigned longest) const {
    const auto& owed = entries_[id];
    std::optional<unsigned> partial;
    std::size_t partial_first = 0;
    for (unsigned units = 1; units <= longest; ++units) {
      const AnswerShape fence = fence_shape(units);
      if (fence.overlaps(request)) continue;
      std::optional<std::size_t> first_same;  // the first owed fence of this length
      bool others = false;                    // an owed answer that is not such a fence looks like it
      for (std::size_t i = 0; i < owed.size(); ++i) {
        if (!owed[i].shape.overlaps(fence)) continue;
        if (owed[i].fence_units == units) {
          if (!first_same) first_same = i;
        } else {
          others = true;
        }
      }
      if (others) continue;
      if (!first_same) return units;  // nobody owes it: its answer settles everything
      const bool clears = std::none_of(owed.begin() + static_cast<std::ptrdiff_t>(*first_same), owed.end(),
                                       [&](const Entry& entry) { return entry.shape.overlaps(request); });
      if (clears) return units;
      if (!partial || *first_same > partial_first) {
        partial = units;
        partial_first = *first_same;
      }
    }
    return partial;
  }
  // A fence of `units` to `id` was answered: what was asked before the first owed fence of that
  // length has come or never will (all of it, when none is owed); what was asked after it may
  // still come (the answer taken may have been that earlier fence's).
  void fence_answered(std::uint8_t id, unsigned units) {
    auto& owed = entries_[id];
    const auto first =
        std::find_if(owed.begin(), owed.end(), [&](const Entry& entry) { return entry.fence_units == units; });
    owed.erase(owed.begin(), first);
  }
  // Nothing can still come from anyone (a reopened line).
  void clear() {
    for (auto& owed : entries_) owed.clear();
  }

  // The attempts of one transaction to `id`: however it ends, those not heard owe an answer of
  // the request's shape. (A late answer to an earlier attempt of the same request is that
  // request's answer all the same.)
  class Tally {
   public:
    Tally(OwedAnswers& owed, std::uint8_t id, AnswerShape shape, bool awaited, unsigned fence_units = 0)
        : owed_(owed), id_(id), shape_(shape), awaited_(awaited), fence_units_(fence_units) {}
    ~Tally() {
      if (awaited_ && sent_ > heard_) owed_.add(id_, shape_, sent_ - heard_, fence_units_, last_sent_);
    }
    Tally(const Tally&) = delete;
    Tally& operator=(const Tally&) = delete;
    void sent(SteadyClock::time_point at = SteadyClock::now()) {
      ++sent_;
      last_sent_ = at;
    }
    void heard() { ++heard_; }  // a valid answer from `id` to one of the attempts (a damaged one may be anyone's)

   private:
    OwedAnswers& owed_;
    std::uint8_t id_;
    AnswerShape shape_;
    bool awaited_;
    unsigned fence_units_;
    unsigned sent_ = 0;
    unsigned heard_ = 0;
    SteadyClock::time_point last_sent_{};
  };

 private:
  struct Entry {
    AnswerShape shape;
    unsigned count = 0;
    unsigned fence_units = 0;
    std::optional<SteadyClock::time_point> waited_since;  // nullopt: sent blind
  };
  std::array<std::vector<Entry>, 256> entries_{};
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
  transactor.owe_answer(request);
  { line.refusal_bits() } -> std::convertible_to<std::uint8_t>;
  { line.status_in_block(block, data) } -> std::same_as<std::optional<std::uint8_t>>;
  line.for_each_write(request, transactor_contract::WriteVisitor{});
  { T::check_servo(servo) } -> std::convertible_to<std::string>;
  // Compile-time constants, not just members of the right type.
  typename std::integral_constant<std::size_t, T::kBytesPerAddress>;
  typename std::bool_constant<T::kAnswersCarryStatus>;
};

}  // namespace sms::gateway
