#include "gateway/bus/rtu_transactor.h"

#include <fmt/format.h>

#include <algorithm>
#include <stdexcept>
#include <variant>

#include "gateway/bus/discovery.h"
#include "protocol/hex_text.h"
#include "protocol/modbus_pdu.h"
#include "protocol/modbus_rtu.h"

namespace sms::gateway {

namespace fc = protocol::function_code;
using protocol::Bytes;

namespace {

constexpr std::uint16_t kMaxReadRegisters = protocol::modbus_limits::kReadRegisters;
constexpr std::uint16_t kMaxWriteRegisters = protocol::modbus_limits::kWriteRegisters;
constexpr std::uint16_t kSmsmbStatusRegister = 0x100;

// SMSMB identity (docs/PROTOCOL.md §2.4, discovery.h): its first register answers PINGs.
const IdentityLayout& smsmb_identity() { return *identity_layout(modbus_map::TableId::Smsmb); }

// A reply's size for the reply timeout: exact where the function says it, else the largest.
std::size_t expected_reply_bytes(std::span<const std::uint8_t> pdu) {
  const auto quantity = [&](std::size_t at) -> std::size_t {
    return pdu.size() >= at + 2 ? static_cast<std::size_t>(pdu[at] << 8 | pdu[at + 1]) : 0;
  };
  switch (pdu[0]) {
    case fc::kReadCoils:
    case fc::kReadDiscreteInputs: return 5 + (quantity(3) + 7) / 8;
    case fc::kReadHoldingRegisters:
    case fc::kReadInputRegisters:
    case fc::kReadWriteMultipleRegisters: return 5 + 2 * quantity(3);
    case fc::kWriteSingleCoil:
    case fc::kWriteSingleRegister:
    case fc::kWriteMultipleCoils:
    case fc::kWriteMultipleRegisters: return 8;
    default: return protocol::rtu::kMaxAduSize;
  }
}

}  // namespace

std::string RtuTransactor::check_servo(const ServoSettings& servo) {
  if (servo.servo_id < 1 || servo.servo_id > kMaxSlave) return "a Modbus slave address is 1-247";
  const auto& block = servo.poll_block;
  if (block.count == 0 || block.count > kMaxReadRegisters || std::uint32_t{block.address} + block.count > 0x10000) {
    return fmt::format("poll block 0x{:04X}+{} cannot be read with one FC03 (1-125 registers)", block.address,
                       block.count);
  }
  return {};
}

RtuTransactor::RtuTransactor(RtuLineSettings line, TransactionTiming timing, BusCounters& counters)
    : master_(std::move(line)), timing_(std::move(timing)), counters_(counters) {}

std::string RtuTransactor::line_description() const {
  const auto baud = master_.settings().serial.baud;
  return fmt::format("modbus-rtu at {} bit/s{}", baud, libmodbus_sets_rate(baud) ? "" : " (termios2 rate)");
}

Expected<Ok> RtuTransactor::set_baud(std::uint32_t baud) { return master_.set_baud(baud); }

// ==== requests =================================================================================

RtuTransactor::Request RtuTransactor::read_request(std::uint8_t slave, AddressBlock block, unsigned attempts) const {
  Request request;
  request.slave = slave;
  request.pdu = protocol::read_holding_registers_pdu(block.address, block.count);
  request.shape = ReplyShape::Registers;
  request.registers = block.count;
  request.no_reply = slave == kBroadcastSlave;  // nobody answers a broadcast (a tool's scan may send one)
  request.attempts = request.no_reply ? 1 : attempts;
  return request;
}

RtuTransactor::Request RtuTransactor::ping_request(std::uint8_t slave, unsigned attempts) const {
  Request request = read_request(slave, {smsmb_identity().read.address, 1}, attempts);
  request.shape = ReplyShape::AnyOfFunction;
  return request;
}

RtuTransactor::Request RtuTransactor::sync_read_request(AddressBlock, const std::vector<std::uint8_t>&) const {
  throw std::logic_error("Modbus RTU has no SYNC READ");
}

RtuTransactor::Request RtuTransactor::prepare(BusOp&& op, unsigned attempts) const {
  const std::string& label = timing_.label;
  Request request;
  request.attempts = attempts;
  if (auto* read = std::get_if<ReadOp>(&op)) {
    if (read->servo_id < 1 || read->servo_id > kMaxSlave) {
      throw std::invalid_argument(label + "FC03 reads go to slaves 1-247, not " + std::to_string(read->servo_id));
    }
    if (read->count < 1 || read->count > kMaxReadRegisters) {
      throw std::invalid_argument(label + "FC03 reads 1-125 registers, not " + std::to_string(read->count));
    }
    return read_request(read->servo_id, {read->address, read->count}, attempts);
  }
  if (auto* write = std::get_if<WriteOp>(&op)) {
    if (write->staged) throw std::invalid_argument(label + "Modbus has no staged (REG WRITE) writes");
    const std::size_t registers = write->data.size() / 2;
    if (write->data.size() % 2 != 0 || registers < 1 || registers > kMaxWriteRegisters) {
      throw std::invalid_argument(label + "a write carries 1-123 registers (2 bytes each), not " +
                                  std::to_string(write->data.size()) + " bytes");
    }
    if (write->servo_id > kMaxSlave) {
      throw std::invalid_argument(label + "writes go to slaves 1-247 or 0 (broadcast), not " +
                                  std::to_string(write->servo_id));
    }
    request.slave = write->servo_id;
    request.pdu = protocol::write_registers_pdu(write->address, write->data);
    request.shape = registers == 1 ? ReplyShape::Echo : ReplyShape::WriteMultiple;
    request.no_reply = write->servo_id == kBroadcastSlave || !write->expect_reply;
  } else if (auto* ping = std::get_if<PingOp>(&op)) {
    if (ping->servo_id < 1 || ping->servo_id > kMaxSlave) {
      throw std::invalid_argument(label + "PING goes to slaves 1-247, not " + std::to_string(ping->servo_id));
    }
    return ping_request(ping->servo_id, attempts);
  } else if (auto* raw = std::get_if<RawPduOp>(&op)) {
    if (raw->pdu.empty() || raw->pdu.size() > protocol::rtu::kMaxPduSize) {
      throw std::invalid_argument(label + "a PDU is 1-253 bytes, not " + std::to_string(raw->pdu.size()));
    }
    if (raw->slave > kMaxSlave) {
      throw std::invalid_argument(label + "slave addresses are 1-247 or 0 (broadcast), not " +
                                  std::to_string(raw->slave));
    }
    request.slave = raw->slave;
    request.pdu = std::move(raw->pdu);
    request.shape = ReplyShape::AnyOfFunction;
    request.forward_exceptions = true;
    request.no_reply = raw->slave == kBroadcastSlave;
  } else if (std::holds_alternative<ActionOp>(op)) {
    throw std::invalid_argument(label + "Modbus has no ACTION: staged writes exist on packet buses only");
  } else if (std::holds_alternative<SyncReadOp>(op)) {
    throw std::invalid_argument(label + "Modbus has no SYNC READ");
  } else {
    throw std::invalid_argument(label + "Modbus has no SYNC WRITE: sync groups need packet buses");
  }
  if (request.no_reply) request.attempts = 1;  // nothing tells whether it arrived: never sent twice
  return request;
}

std::optional<std::uint8_t> RtuTransactor::status_in_block(const AddressBlock& block,
                                                           std::span<const std::uint8_t> data) const {
  if (!block.contains(kSmsmbStatusRegister, 1)) return std::nullopt;
  const auto offset = static_cast<std::size_t>(kSmsmbStatusRegister - block.address) * 2;
  if (offset + 1 >= data.size()) return std::nullopt;
  return data[offset + 1];
}

// ==== one transaction ==========================================================================

std::string RtuTransactor::what_for(const Request& request) {
  return fmt::format("before FC{:02X} to slave {}", request.pdu[0], request.slave);
}

std::string RtuTransactor::where(const Request& request) const {
  return fmt::format("{}slave {} FC{:02X}", timing_.label, request.slave, request.pdu[0]);
}

AnswerShape RtuTransactor::answer_shape(const Request& request) {
  constexpr std::size_t kException = AnswerShape::kExceptionLength;
  const std::uint8_t function = request.pdu[0];
  if (request.fence_units != 0) return AnswerShape::of(function, {2 + std::size_t{request.registers} * 2});
  switch (request.shape) {
    case ReplyShape::Registers: return AnswerShape::of(function, {2 + std::size_t{request.registers} * 2, kException});
    case ReplyShape::Echo:
    case ReplyShape::WriteMultiple: return AnswerShape::of(function, {5, kException});
    case ReplyShape::AnyOfFunction: break;
  }
  AnswerShape any{function, {}};
  any.lengths.set();
  return any;
}

AnswerShape RtuTransactor::frame_shape(std::span<const std::uint8_t> pdu) {
  if (pdu.empty()) return {};
  const bool exception = (pdu[0] & fc::kExceptionBit) != 0;
  return AnswerShape::frame(static_cast<std::uint8_t>(pdu[0] & ~fc::kExceptionBit),
                            exception ? AnswerShape::kExceptionLength : pdu.size());
}

void RtuTransactor::note_late_answers(std::span<const std::uint8_t> dropped, TransactionEvents& events) {
  std::size_t at = 0;
  while (dropped.size() - at >= 5) {
    const std::uint8_t function = dropped[at + 1];
    std::size_t length = 0;  // slave, PDU, CRC
    if ((function & fc::kExceptionBit) != 0) {
      length = 5;
    } else if (function == fc::kReadHoldingRegisters || function == fc::kReadInputRegisters) {
      length = 5 + std::size_t{dropped[at + 2]};
    } else if (function == fc::kWriteSingleRegister || function == fc::kWriteMultipleRegisters) {
      length = 8;
    }
    const auto frame = dropped.subspan(at, std::min(length, dropped.size() - at));
    const bool whole = length != 0 && frame.size() == length &&
                       protocol::rtu::crc16(frame.first(length - 2)) == (frame[length - 2] | frame[length - 1] << 8);
    if (!whole) {
      ++at;  // noise, or a frame cut short: look for one further on
      continue;
    }
    const std::uint8_t slave = frame[0];
    const auto arrival = owed_.arrived(slave, frame_shape(frame.subspan(1, length - 3)));
    if (arrival.late_since) {
      (void)events.late(
          slave, std::chrono::duration_cast<std::chrono::milliseconds>(SteadyClock::now() - *arrival.late_since));
    }
    at += length;
  }
}

std::optional<BusResult> RtuTransactor::fence_before(const Request& request, TransactionEvents& events) {
  const AnswerShape shape = answer_shape(request);
  const auto fence_shape = [](unsigned units) {
    return AnswerShape::of(fc::kReadHoldingRegisters, {2 + std::size_t{units} * 2});
  };
  // Each fence settles at least what came before the first owed fence of its length; a few are
  // enough for any list a slave can owe (transactor.h OwedAnswers).
  for (unsigned round = 0; owed_.collides(request.slave, shape); ++round) {
    const auto units = owed_.fence_length(request.slave, fence_shape, shape, kLongestFence);
    if (!units || round == kLongestFence) {
      // Not reachable with the fence lengths there are; said rather than looped on.
      spdlog::warn("{}: slave {} owes {} late answers no fence can be told from: they are forgotten", where(request),
                   request.slave, owed_.count(request.slave));
      owed_.settled(request.slave);
      return std::nullopt;
    }
    // SMSMB: registers 0x00-0x03 (firmware, version, date) for the short fences, the feedback block
    // 0x100-0x107 for the longer ones: both read on every SMSMB servo.
    const std::uint16_t address = *units <= 4 ? 0x00 : kSmsmbStatusRegister;
    Request fence = read_request(request.slave, {address, static_cast<std::uint16_t>(*units)}, request.attempts);
    fence.fence_units = *units;
    counters_.fences.fetch_add(1, std::memory_order_relaxed);
    BusResult fenced = transact(fence, events);
    if (fenced.status == BusStatus::Ok) continue;
    if (fenced.status != BusStatus::BusDown) {
      fenced.detail += fmt::format(
          " (a fence before FC{:02X}: slave {} still owes late answers that could look like its answer; the request "
          "was not sent)",
          request.pdu[0], request.slave);
    }
    return fenced;
  }
  return std::nullopt;
}

BusResult RtuTransactor::execute(const Request& request, TransactionEvents& events) {
  if (request.no_reply) {
    const RtuExchange sent = master_.send_only(request.slave, request.pdu, timing_.reply_allowance);
    if (sent.outcome == RtuOutcome::PortError) return BusResult{BusStatus::BusDown, 0, {}, sent.detail};
    stray_.count(sent.dropped.size(), timing_.label, [&] { return what_for(request); });
    note_late_answers(sent.dropped, events);
    return BusResult{};
  }
  if (auto not_sent = fence_before(request, events)) return std::move(*not_sent);
  return transact(request, events);
}

BusResult RtuTransactor::transact(const Request& request, TransactionEvents& events) {
  // The reply timeout counts from when the request has left the wire (RtuMaster adds that).
  const auto reply_timeout = master_.wire_time(expected_reply_bytes(request.pdu)) + timing_.reply_allowance;
  OwedAnswers::Tally tally(owed_, request.slave, answer_shape(request), true, request.fence_units);
  bool corrupt = false;
  std::string last_problem;
  for (unsigned attempt = 0; attempt < request.attempts; ++attempt) {
    if (attempt > 0) counters_.retries.fetch_add(1, std::memory_order_relaxed);
    tally.sent(SteadyClock::now());
    const auto deadline = SteadyClock::now() + master_.wire_time(request.pdu.size() + 3) + reply_timeout;
    RtuExchange exchange = master_.transact(request.slave, request.pdu, reply_timeout);
    stray_.count(exchange.dropped.size(), timing_.label, [&] { return what_for(request); });
    note_late_answers(exchange.dropped, events);
    // A valid frame from the addressed slave that is not this request's answer is one it owed to
    // an earlier request: dropped and counted, and this attempt's own answer awaited until its deadline.
    while (exchange.outcome == RtuOutcome::Reply) {
      BusResult result = check_reply(request, exchange.pdu);
      if (result.status != BusStatus::Corrupt) {
        tally.heard();
        if (request.fence_units != 0) {
          owed_.fence_answered(request.slave, request.fence_units);
        } else {
          owed_.settled(request.slave);  // only this request's answer looks like this
        }
        counters_.frames_ok.fetch_add(1, std::memory_order_relaxed);
        events.answered(request.slave, std::nullopt);
        if (attempt == 0) events.answered_in_time(request.slave);
        return result;
      }
      const auto arrival = owed_.arrived(request.slave, frame_shape(exchange.pdu));
      counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
      events.foreign(request.slave);
      if (arrival.late_since && events.late(request.slave, std::chrono::duration_cast<std::chrono::milliseconds>(
                                                               SteadyClock::now() - *arrival.late_since))) {
        // Its own answer will be as late: waiting for it, and asking again, costs the bus.
        return BusResult{BusStatus::Timeout,
                         0,
                         {},
                         where(request) + ": the slave answers late (after its reply timeout): not asked again"};
      }
      spdlog::debug("{}: dropped a frame that is not its answer ({})", where(request), result.detail);
      last_problem = result.detail;
      const auto left = deadline - SteadyClock::now();
      if (left <= std::chrono::nanoseconds::zero()) {
        exchange = RtuExchange{RtuOutcome::Timeout, {}, "only answers to earlier requests came: " + last_problem};
        break;
      }
      exchange = master_.receive(request.slave, request.pdu[0], left);
    }
    switch (exchange.outcome) {
      case RtuOutcome::Reply: break;  // handled above
      case RtuOutcome::Timeout:
        counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
        events.unanswered(request.slave);
        last_problem = exchange.detail;
        break;
      case RtuOutcome::Corrupt:
        // A damaged answer ends the attempt. It is not counted as this request's: it may have
        // been an owed one, and this request's answer may still come.
        counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
        events.damaged();
        corrupt = true;
        last_problem = exchange.detail;
        break;
      case RtuOutcome::WrongSlave:
        counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
        if (exchange.other_slave) {
          events.foreign(*exchange.other_slave);
        } else {
          events.damaged();
        }
        corrupt = true;
        last_problem = exchange.detail;
        break;
      case RtuOutcome::PortError: return BusResult{BusStatus::BusDown, 0, {}, exchange.detail};
      case RtuOutcome::Sent: break;
    }
  }
  const auto attempts = fmt::format("{} attempt{}", request.attempts, request.attempts == 1 ? "" : "s");
  if (corrupt) {
    return BusResult{
        BusStatus::Corrupt, 0, {}, where(request) + ": answers stayed corrupt (" + attempts + "): " + last_problem};
  }
  return BusResult{BusStatus::Timeout, 0, {}, where(request) + ": no answer (" + attempts + "): " + last_problem};
}

BusResult RtuTransactor::check_reply(const Request& request, Bytes reply) const {
  const std::uint8_t requested = request.pdu[0];
  const auto corrupt = [&](std::string_view what) {
    return BusResult{
        BusStatus::Corrupt, 0, {}, fmt::format("{}: {}: {}", where(request), what, protocol::hex_bytes(reply))};
  };
  if (reply.empty()) return corrupt("empty answer");
  if (reply[0] == (requested | fc::kExceptionBit)) {
    if (reply.size() != 2) return corrupt("malformed exception answer");
    if (request.fence_units != 0) return corrupt("an exception answers no fence (it may be an owed answer's)");
    if (request.forward_exceptions || request.shape == ReplyShape::AnyOfFunction) {
      return BusResult{BusStatus::Ok, reply[1], std::move(reply), {}};
    }
    return BusResult{BusStatus::ServoRefused,
                     reply[1],
                     {},
                     fmt::format("{}: the slave answered exception 0x{:02X} ({})", where(request), reply[1],
                                 protocol::modbus_exception_name(reply[1]))};
  }
  if (reply[0] != requested) return corrupt(fmt::format("answer with function 0x{:02X}", reply[0]));
  switch (request.shape) {
    case ReplyShape::Registers: {
      const std::size_t bytes = std::size_t{request.registers} * 2;
      if (reply.size() != 2 + bytes || reply[1] != bytes) return corrupt("register count differs from the request");
      return BusResult{BusStatus::Ok, 0, Bytes(reply.begin() + 2, reply.end()), {}};
    }
    case ReplyShape::Echo:
      if (reply != request.pdu) return corrupt("FC06 answer is not the echo of the request");
      return BusResult{};
    case ReplyShape::WriteMultiple:
      if (reply.size() != 5 || !std::equal(reply.begin(), reply.end(), request.pdu.begin())) {
        return corrupt("FC16 answer does not repeat address and quantity");
      }
      return BusResult{};
    case ReplyShape::AnyOfFunction: return BusResult{BusStatus::Ok, 0, std::move(reply), {}};
  }
  return corrupt("unexpected answer");
}

}  // namespace sms::gateway
