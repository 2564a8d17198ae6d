#pragma once
// The narrow, per-protocol part of a bus: one transaction at a time, synchronously, on the
// calling thread — the bus engine's thread (engine_core.h) or an integrator tool's main thread
// (gateway/tools/tool_link.cpp). Two transactors exist:
//   PacketTransactor (packet_transactor.h): feetech `FF FF` and d55d `D5 5D` packets through
//                     SerialPort and the stream decoder;
//   RtuTransactor    (rtu_transactor.h):    Modbus RTU through libmodbus (RtuMaster).
// Each has the same face, which the engine core is written against (a template parameter, so
// each protocol keeps its own request type):
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
//
// Bus-wide counters (frames, timeouts, checksum errors, stray frames, retries, discarded bytes)
// are counted by the transactor into the BusCounters it is given; what concerns one servo is
// reported through TransactionEvents, so the engine keeps its per-servo counters, status byte
// and presence, and a tool learns what it heard.
#include <chrono>
#include <cstdint>
#include <optional>
#include <span>
#include <string>

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

}  // namespace sms::gateway
