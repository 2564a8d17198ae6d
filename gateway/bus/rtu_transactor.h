#pragma once
// One transaction on a `modbus-rtu` bus (docs/PROTOCOL.md §1.3) through RtuMaster (libmodbus), with the
// face of transactor.h. Bus operations in Modbus terms:
//   ReadOp   -> FC03 (read holding registers; SMSMB servos have no FC04, docs/PROTOCOL.md §1.3)
//   WriteOp  -> FC06 for one register, FC16 for more; servo 0 is a broadcast (no reply)
//   PingOp   -> FC03 of register 0 (any answer, an exception too, means "present")
//   RawPduOp -> the PDU as it is (passthrough); the reply PDU comes back as it is, exception
//               PDUs included; slave 0 is a broadcast
//   poll     -> one FC03 per servo per cycle over its poll block (no batched read exists)
// ActionOp, SyncWriteOp and staged writes have no Modbus form: prepare() throws.
//
// Answers are checked against the request: FC03 must carry the registers asked for, FC06 must
// echo the request, FC16 must repeat address and quantity; anything else from the addressed
// slave is taken for an answer it owed to an earlier request: dropped, counted as stray, and the
// attempt's own answer awaited. Late answers are guarded against as transactor.h says: the input
// is read and dropped before each request, and a request whose answer could look like one its
// slave still owes is preceded by a fence read. An exception answer is a refusal
// (ServoRefused with the code as servo_error), except for PING and passthrough, where it is the answer.
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/bus_operations.h"
#include "gateway/bus/poll_cache.h"
#include "gateway/bus/rtu_master.h"
#include "gateway/bus/transactor.h"

namespace sms::gateway {

class RtuTransactor {
 public:
  // The answer a request waits for.
  enum class ReplyShape : std::uint8_t {
    Registers,      // FC03: byte count 2n, n registers
    Echo,           // FC06: the request PDU itself
    WriteMultiple,  // FC16: function, address, quantity (the request's first five bytes)
    AnyOfFunction,  // passthrough and PING: any answer to this function code, exceptions included
  };
  struct Request {
    std::uint8_t slave = 0;
    protocol::Bytes pdu;
    ReplyShape shape = ReplyShape::AnyOfFunction;
    std::uint16_t registers = 0;      // Registers: how many
    bool no_reply = false;            // slave 0, or a write the servo does not answer
    bool forward_exceptions = false;  // RawPduOp: an exception PDU is the answer, passed on as it is
    unsigned attempts = 1;
    unsigned fence_units = 0;  // a fence (transactor.h "Late answers"): only its registers are its answer
  };

  static constexpr std::uint8_t kBroadcastSlave = 0;
  static constexpr std::uint8_t kMaxSlave = 247;
  static constexpr std::size_t kBytesPerAddress = 2;  // registers, high byte first as on the wire
  // Fences (transactor.h "Late answers") read 1..8 registers (fence_before() says where).
  static constexpr unsigned kLongestFence = 8;
  static constexpr bool kAnswersCarryStatus = false;  // SMSMB's status is register 0x100 (status_in_block)

  // Why the bus cannot poll `servo` (its slave address or poll block is out of Modbus's reach);
  // empty when it can.
  static std::string check_servo(const ServoSettings& servo);

  // `counters` outlives the transactor.
  RtuTransactor(RtuLineSettings line, TransactionTiming timing, BusCounters& counters);

  Expected<Ok> open() {
    owed_.clear();  // a reopened line: nothing sent before can still be answered on it
    return master_.open();
  }
  void close() { master_.close(); }
  bool is_open() const { return master_.is_open(); }
  std::string line_description() const;
  std::string_view protocol_name() const { return "modbus-rtu"; }
  // Changes the line rate (reopening the line when it is open).
  Expected<Ok> set_baud(std::uint32_t baud);
  void set_reply_allowance(std::chrono::nanoseconds allowance) { timing_.reply_allowance = allowance; }
  // Records the line's traffic in the bus monitor (wire_monitor.h); nullptr: none.
  void set_monitor(WireMonitor* monitor) { master_.set_monitor(monitor); }

  Request prepare(BusOp&& op, unsigned attempts) const;
  Request read_request(std::uint8_t slave, AddressBlock block, unsigned attempts) const;
  Request ping_request(std::uint8_t slave, unsigned attempts) const;
  Request sync_read_request(AddressBlock, const std::vector<std::uint8_t>&) const;  // throws: Modbus has none
  static std::uint8_t target(const Request& request) { return request.slave; }
  static bool broadcast(const Request& request) { return broadcast_id(request.slave); }
  static bool broadcast_id(std::uint8_t slave) { return slave == kBroadcastSlave; }
  static constexpr bool has_sync_read() { return false; }

  BusResult execute(const Request& request, TransactionEvents& events);
  // The answer to `request` may come although it was not awaited (the same write was sent blind):
  // a later request its answer could be taken for goes behind a fence.
  void owe_answer(const Request& request) {
    if (!request.no_reply) owed_.add(request.slave, answer_shape(request), 1, 0, std::nullopt);  // sent blind
  }

  // Modbus answers carry no status byte: nothing is only about the instruction.
  std::uint8_t refusal_bits() const { return 0; }
  // SMSMB status register 0x100: its low byte is what input register 1000 shows as "last status".
  std::optional<std::uint8_t> status_in_block(const AddressBlock& block, std::span<const std::uint8_t> data) const;
  // SMSMB servos have no response-level field: what a write wrote changes nothing the engine keeps.
  template <typename Fn>
  void for_each_write(const Request&, Fn&&) const {}

 private:
  // Every answer `request` would take, and the shape of one that came (transactor.h AnswerShape:
  // function code, PDU length or an exception).
  static AnswerShape answer_shape(const Request& request);
  static AnswerShape frame_shape(std::span<const std::uint8_t> pdu);
  // When the slave owes answers that could look like `request`'s: the fence read first; nullopt
  // when the request may go, otherwise why it did not.
  std::optional<BusResult> fence_before(const Request& request, TransactionEvents& events);
  // The bytes dropped before a request, which came while the line was idle: each whole frame
  // among them (its length from its function code, its CRC right) that a slave owed is taken off
  // its owed answers, and told to `events` as late where it was (as the packet buses do).
  void note_late_answers(std::span<const std::uint8_t> dropped, TransactionEvents& events);
  BusResult transact(const Request& request, TransactionEvents& events);
  BusResult check_reply(const Request& request, protocol::Bytes reply) const;
  std::string where(const Request& request) const;
  static std::string what_for(const Request& request);  // "before FC03 to slave 1", for the stray count

  RtuMaster master_;
  TransactionTiming timing_;
  BusCounters& counters_;
  OwedAnswers owed_;
  StrayBytes stray_{counters_};
};

}  // namespace sms::gateway
