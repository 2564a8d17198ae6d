#pragma once
// One transaction on a packet bus, feetech `FF FF` or d55d `D5 5D` (docs/PROTOCOL.md §1.1, §1.2): one code
// path, parameterised by protocol::PacketFormat and a row of protocol rules (packet_rules.h:
// which ERROR bits mean "refused", whether SYNC READ exists). The face is transactor.h's.
//
// How a transaction runs (docs/PROTOCOL.md §1.1 "host practice"):
// - when the addressed servo owes answers to requests that gave up that could look like this
//   request's answer, a fence read goes first (transactor.h "Late answers"); drop and count what
//   the input holds; transmit, then wait for the answer until a deadline sized from the request's and the
//   reply's wire time plus the reply allowance — extended while bytes are still arriving at the
//   deadline, until the line is quiet (bounded by one more timeout), so a retry never starts
//   into the tail of a late answer;
// - the decoder hunts for the header and resynchronises after garbage; only a frame from the
//   addressed ID with the expected shape is the answer — a late reply from another servo, or a
//   reply of another length, is counted as stray and waited past; a frame identical to the
//   request (an adapter's echo) is taken only if nothing else comes and the adapter has not
//   been seen to echo (a frame identical to a request that it cannot answer, or one followed
//   by the answer): behind an echoing adapter, the echo of a PING to an absent servo is not
//   taken for its answer;
// - after a damaged answer from the addressed servo no valid one follows: the attempt ends as
//   soon as the line is quiet (transmitting into the tail of a frame would collide);
// - the answer to every unicast WRITE is consumed before the next transmit; broadcasts (ACTION,
//   SYNC WRITE, writes to a servo that does not answer writes) complete once drained from the
//   port and their wire time has passed;
// - SYNC READ: each listed servo answers after the one before it; the wait restarts after each
//   answer, and the transaction ends at the first silence (who stayed silent is the engine's to
//   follow up);
// - no valid answer: retry up to the request's attempts; then Timeout, or Corrupt when damaged
//   frames were all that came back.
//
// Decision (refusals, docs/PLC_GUIDE.md 0x04): the refusal bits are d55d's instruction (bit 5) and
// checksum (bit 4) error bits; checksum alone means our frame arrived damaged, so the frame
// is sent again first. Feetech `sts`/`sms1` have no instruction-error bit; their firmware sets
// bit 4 ("angle", also "instruction out of range") in the answer to a write it does not take,
// so bit 4 is feetech's refusal bit. A refusal bit counts only where the answer cannot be
// anything else: in the answer to WRITE / REG WRITE, and in an answer to READ that lacks its
// data. An answer carrying the data asked for, and every PING answer, is an answer: its ERROR
// bits are status (recorded as the servo's last status byte), not an error.
//
// A PING to the broadcast ID (the tools' rate scan) is answered by whoever is there: the first
// valid frame is the answer, and colliding answers end the attempts (something is there).
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/bus_operations.h"
#include "gateway/bus/packet_rules.h"
#include "gateway/bus/poll_cache.h"
#include "gateway/bus/serial_port.h"
#include "gateway/bus/transactor.h"
#include "protocol/expected.h"
#include "protocol/instructions.h"
#include "protocol/packet.h"
#include "protocol/stream_decoder.h"

namespace sms::gateway {

class PacketTransactor {
 public:
  struct Request {
    protocol::Packet packet;
    protocol::Bytes frame;  // encoded once, sent on every attempt
    ReplyKind reply = ReplyKind::None;
    std::uint8_t servo_id = protocol::kBroadcastId;
    std::uint8_t count = 0;  // Data, SyncRead: parameters expected per answer
    std::vector<std::uint8_t> sync_ids;
    unsigned attempts = 1;
    unsigned fence_units = 0;  // a fence (transactor.h "Late answers"): only its data is its answer
  };

  static constexpr std::size_t kBytesPerAddress = 1;  // packet tables address bytes
  // Fences (transactor.h "Late answers") read 1..16 bytes from address 0: every table's start.
  static constexpr unsigned kLongestFence = 16;
  static constexpr bool kAnswersCarryStatus = true;  // every answer's ERROR byte

  // Why the bus cannot poll `servo` (its ID or poll block is out of this protocol's reach);
  // empty when it can.
  static std::string check_servo(const ServoSettings& servo);

  // `protocol` must be feetech or d55d (std::invalid_argument otherwise). `counters` outlives
  // the transactor.
  PacketTransactor(protocol::BusProtocol protocol, SerialSettings serial, TransactionTiming timing,
                   BusCounters& counters);

  Expected<Ok> open();
  void close() { port_.close(); }
  bool is_open() const { return port_.is_open(); }
  std::string line_description() const;
  std::string_view protocol_name() const;
  // Changes the line rate on the open descriptor (a reopen could meet EBUSY while someone else
  // holds the tty); on a closed port, the rate of the next open().
  Expected<Ok> set_baud(std::uint32_t baud);
  void set_reply_allowance(std::chrono::nanoseconds allowance) { timing_.reply_allowance = allowance; }
  // Records the line's traffic in the bus monitor (wire_monitor.h); nullptr: none.
  void set_monitor(WireMonitor* monitor) { port_.set_monitor(monitor); }

  Request prepare(BusOp&& op, unsigned attempts) const;
  Request read_request(std::uint8_t servo_id, AddressBlock block, unsigned attempts) const;
  Request ping_request(std::uint8_t servo_id, unsigned attempts) const;
  // An instruction without parameters to one servo, acknowledged by a status packet (the tools'
  // factory reset: d55d RESET).
  Request instruction_request(std::uint8_t servo_id, std::uint8_t instruction, unsigned attempts) const;
  Request sync_read_request(AddressBlock block, std::vector<std::uint8_t> ids) const;
  static std::uint8_t target(const Request& request) { return request.servo_id; }
  static bool broadcast(const Request& request) { return broadcast_id(request.servo_id); }
  static bool broadcast_id(std::uint8_t id) { return id == protocol::kBroadcastId; }
  bool has_sync_read() const { return rules_.has_sync_read; }

  BusResult execute(const Request& request, TransactionEvents& events);
  // The answer to `request` may come although it was not awaited (the same write was sent blind):
  // a later request its answer could be taken for goes behind a fence.
  void owe_answer(const Request& request) {
    if (request.reply != ReplyKind::None && !broadcast(request))
      owed_.add(request.servo_id, answer_shape(request), 1, 0, std::nullopt);  // sent blind
  }

  std::uint8_t refusal_bits() const { return rules_.refusal_bits; }
  // Packet answers carry the status in every frame: nothing to take from the polled block.
  std::optional<std::uint8_t> status_in_block(const AddressBlock&, std::span<const std::uint8_t>) const {
    return std::nullopt;
  }
  // What a finished `request` wrote: fn(servo or the broadcast ID, address, data) per target.
  // Nothing for requests that write nothing (reads, PING, ACTION).
  template <typename Fn>
  void for_each_write(const Request& request, Fn&& fn) const {
    const protocol::Packet& packet = request.packet;
    if (packet.code == protocol::common::kWrite && packet.params.size() >= 2) {
      fn(packet.id, packet.params[0], std::span<const std::uint8_t>(packet.params).subspan(1));
    } else if (packet.code == protocol::common::kSyncWrite) {
      if (const auto sync = protocol::parse_sync_write(packet.params)) {
        for (const auto& entry : sync->entries) fn(entry.id, sync->address, entry.data);
      }
    }
  }

 private:
  struct AttemptFindings;
  class EchoRule;     // an adapter's echo of our frame: when it is the answer
  class Transaction;  // one execute(): its attempts as named steps

  // "READ 56+15 of servo 1", for messages.
  std::string describe(const Request& request) const;
  Request finish_request(Request request) const;
  BusResult fail(const Request& request, const AttemptFindings& last, unsigned attempts_made) const;
  BusResult port_lost(const std::string& reason);
  void count_discarded();
  // Every answer `request` would take (transactor.h AnswerShape: parameter counts; a refusal
  // carries none).
  AnswerShape answer_shape(const Request& request) const;
  // When `request`'s servo owes answers that could look like its answer: the fence read first.
  // nullopt: the request may go; otherwise why it did not (the fence went unanswered).
  std::optional<BusResult> fence_before(const Request& request, TransactionEvents& events);
  const PacketRules& rules_;
  SerialPort port_;
  TransactionTiming timing_;
  BusCounters& counters_;
  protocol::StreamDecoder decoder_;
  std::size_t decoder_discarded_seen_ = 0;
  bool adapter_echoes_ = false;  // learnt: this line hands our own frames back
  OwedAnswers owed_;
  StrayBytes stray_{counters_};
  std::chrono::nanoseconds quiet_gap_;
  std::array<std::uint8_t, 512> rx_buffer_{};
};

}  // namespace sms::gateway
