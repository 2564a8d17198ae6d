#include "gateway/bus/packet_transactor.h"

#include <fmt/format.h>
#include <spdlog/fmt/bin_to_hex.h>
#include <spdlog/spdlog.h>

#include <bitset>
#include <stdexcept>
#include <thread>
#include <utility>
#include <variant>

#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"

namespace sms::gateway {

using namespace std::chrono_literals;
using protocol::Packet;

namespace {

std::string join_ids(std::span<const std::uint8_t> ids) {
  std::string text;
  for (const auto id : ids) {
    if (!text.empty()) text += ',';
    text += std::to_string(id);
  }
  return text;
}

double to_ms(std::chrono::nanoseconds duration) { return static_cast<double>(duration.count()) / 1e6; }

}  // namespace

// What the attempts of one transaction learnt, for the verdict after the last one.
struct PacketTransactor::AttemptFindings {
  bool damaged_any = false;      // a damaged frame came back on some attempt
  bool refused_damaged = false;  // d55d checksum bit seen: our frame arrived damaged
  std::uint8_t last_error = 0;
  std::chrono::nanoseconds timeout{};  // for messages
};

std::string PacketTransactor::check_servo(const ServoSettings& servo) {
  if (servo.servo_id >= protocol::kBroadcastId) return "a servo ID is 0-253";
  const auto& block = servo.poll_block;
  if (block.count == 0 || block.count > protocol::kMaxParams || block.address > 0xFF || block.end() > 0x100) {
    return fmt::format("poll block {}+{} cannot be read in one READ (byte addresses 0-255, 1-253 bytes)", block.address,
                       block.count);
  }
  return {};
}

PacketTransactor::PacketTransactor(protocol::BusProtocol protocol, SerialSettings serial, TransactionTiming timing,
                                   BusCounters& counters)
    : rules_(packet_rules(protocol)),
      port_(std::move(serial)),
      timing_(std::move(timing)),
      counters_(counters),
      decoder_(*rules_.format),
      quiet_gap_(wire_time(port_.settings(), 32) + 1ms) {}

Expected<Ok> PacketTransactor::open() {
  auto opened = port_.open();
  if (!opened) return opened;
  const auto wanted = port_.settings().baud;
  const auto actual = port_.actual_baud();
  if (actual != wanted && (actual > wanted ? actual - wanted : wanted - actual) * 100 > wanted) {
    spdlog::warn("{}{} runs at {} bit/s instead of {} (the adapter rounds this rate): frames may be garbled",
                 timing_.label, port_.settings().device, actual, wanted);
  }
  decoder_.reset();
  count_discarded();
  owed_.clear();  // a reopened line: nothing sent before can still be answered on it
  return Ok{};
}

std::string PacketTransactor::line_description() const {
  const SerialSettings& serial = port_.settings();
  return fmt::format("{} at {} bit/s, {} parity, {} stop bit{}", rules_.format->name, serial.baud,
                     config::to_string(serial.parity), serial.stop_bits, serial.stop_bits == 1 ? "" : "s");
}

std::string_view PacketTransactor::protocol_name() const { return rules_.format->name; }

Expected<Ok> PacketTransactor::set_baud(std::uint32_t baud) { return port_.set_baud(baud); }

// ==== requests =================================================================================

PacketTransactor::Request PacketTransactor::finish_request(Request request) const {
  request.frame = protocol::encode(*rules_.format, request.packet);
  return request;
}

PacketTransactor::Request PacketTransactor::read_request(std::uint8_t servo_id, AddressBlock block,
                                                         unsigned attempts) const {
  Request request;
  request.packet =
      protocol::read(servo_id, static_cast<std::uint8_t>(block.address), static_cast<std::uint8_t>(block.count));
  request.reply = ReplyKind::Data;
  request.servo_id = servo_id;
  request.count = static_cast<std::uint8_t>(block.count);
  request.attempts = attempts;
  return finish_request(std::move(request));
}

PacketTransactor::Request PacketTransactor::ping_request(std::uint8_t servo_id, unsigned attempts) const {
  Request request;
  request.packet = protocol::ping(servo_id);
  request.reply = ReplyKind::Ping;
  request.servo_id = servo_id;
  request.attempts = attempts;
  return finish_request(std::move(request));
}

PacketTransactor::Request PacketTransactor::instruction_request(std::uint8_t servo_id, std::uint8_t instruction,
                                                                unsigned attempts) const {
  Request request;
  request.packet = protocol::Packet{servo_id, instruction, {}};
  request.reply = ReplyKind::Ack;
  request.servo_id = servo_id;
  request.attempts = attempts;
  return finish_request(std::move(request));
}

PacketTransactor::Request PacketTransactor::sync_read_request(AddressBlock block, std::vector<std::uint8_t> ids) const {
  if (!rules_.has_sync_read) throw std::logic_error("SYNC READ on a protocol without it");
  Request request;
  request.packet = protocol::feetech::sync_read(static_cast<std::uint8_t>(block.address),
                                                static_cast<std::uint8_t>(block.count), ids);
  request.reply = ReplyKind::SyncRead;
  request.count = static_cast<std::uint8_t>(block.count);
  request.sync_ids = std::move(ids);
  request.attempts = 1;  // who stays silent is read on its own, with retries, by the engine
  return finish_request(std::move(request));
}

PacketTransactor::Request PacketTransactor::prepare(BusOp&& op, unsigned attempts) const {
  // Messages are built only for a request that is refused: this runs for every client request.
  const auto refuse = [this](const std::string& what) { return std::invalid_argument(timing_.label + what); };
  Request request;
  request.attempts = attempts;
  if (auto* read = std::get_if<ReadOp>(&op)) {
    if (read->servo_id >= protocol::kBroadcastId) throw refuse("READ needs one servo ID (0-253), not the broadcast ID");
    if (read->address > 0xFF) throw refuse("READ address " + std::to_string(read->address) + " is not a byte address");
    if (read->count < 1 || read->count > protocol::kMaxParams) {
      throw refuse("READ of " + std::to_string(read->count) + " bytes: one READ returns 1-253 bytes");
    }
    return read_request(read->servo_id, {read->address, read->count}, attempts);
  }
  if (auto* write = std::get_if<WriteOp>(&op)) {
    if (write->address > 0xFF)
      throw refuse("WRITE address " + std::to_string(write->address) + " is not a byte address");
    if (write->data.empty() || write->data.size() >= protocol::kMaxParams) {
      throw refuse("WRITE of " + std::to_string(write->data.size()) + " bytes: one WRITE carries 1-252 bytes");
    }
    const auto address = static_cast<std::uint8_t>(write->address);
    request.packet = write->staged ? protocol::reg_write(write->servo_id, address, write->data)
                                   : protocol::write(write->servo_id, address, write->data);
    request.servo_id = write->servo_id;
    // Broadcast writes are never answered (docs/PROTOCOL.md §1).
    request.reply =
        (write->expect_reply && write->servo_id != protocol::kBroadcastId) ? ReplyKind::Ack : ReplyKind::None;
  } else if (std::holds_alternative<ActionOp>(op)) {
    request.packet = protocol::action();
  } else if (auto* sync = std::get_if<SyncWriteOp>(&op)) {
    if (sync->address > 0xFF) {
      throw refuse("SYNC WRITE address " + std::to_string(sync->address) + " is not a byte address");
    }
    if (sync->entries.empty()) throw refuse("SYNC WRITE without servos");
    try {
      request.packet = protocol::sync_write(static_cast<std::uint8_t>(sync->address), sync->length, sync->entries);
    } catch (const std::exception& error) {
      throw refuse(std::string("SYNC WRITE: ") + error.what());
    }
  } else if (auto* sync_read = std::get_if<SyncReadOp>(&op)) {
    if (!rules_.has_sync_read) {
      throw refuse("SYNC READ does not exist on a " + std::string(protocol::to_string(rules_.protocol)) + " bus");
    }
    if (sync_read->ids.empty() || sync_read->address > 0xFF || sync_read->count < 1 ||
        sync_read->count > protocol::kMaxParams) {
      throw refuse("SYNC READ needs servos, a byte address and 1-253 bytes");
    }
    return sync_read_request({sync_read->address, sync_read->count}, std::move(sync_read->ids));
  } else if (auto* ping = std::get_if<PingOp>(&op)) {
    if (ping->servo_id >= protocol::kBroadcastId) {
      throw refuse("PING needs one servo ID (0-253): answers to a broadcast collide");
    }
    return ping_request(ping->servo_id, attempts);
  } else {
    throw refuse("a raw Modbus PDU cannot be sent on a " + std::string(protocol::to_string(rules_.protocol)) + " bus");
  }
  // Nothing tells whether an unanswered frame arrived: it is never sent twice.
  if (request.reply == ReplyKind::None) request.attempts = 1;
  return finish_request(std::move(request));
}

std::string PacketTransactor::describe(const Request& request) const {
  const auto name = rules_.instruction_name(request.packet.code).value_or("instruction");
  const auto& params = request.packet.params;
  switch (request.reply) {
    case ReplyKind::Data:
      return fmt::format("{} {}+{} of servo {}", name, params.at(0), params.at(1), request.servo_id);
    case ReplyKind::Ack:
      if (params.empty()) return fmt::format("{} to servo {}", name, request.servo_id);
      return fmt::format("{} at {} ({} bytes) to servo {}", name, params.at(0), params.size() - 1, request.servo_id);
    case ReplyKind::Ping:
      if (broadcast(request)) return fmt::format("broadcast {}", name);
      return fmt::format("{} of servo {}", name, request.servo_id);
    case ReplyKind::SyncRead:
      return fmt::format("{} {}+{} of servos {}", name, params.at(0), params.at(1), join_ids(request.sync_ids));
    case ReplyKind::None: break;
  }
  if (broadcast(request)) return fmt::format("broadcast {}", name);
  return fmt::format("{} to servo {} (not answered)", name, request.servo_id);
}

// ==== one transaction ==========================================================================

void PacketTransactor::count_discarded() {
  const auto total = decoder_.discarded_bytes();
  counters_.discarded_bytes.fetch_add(total - decoder_discarded_seen_, std::memory_order_relaxed);
  decoder_discarded_seen_ = total;
}

BusResult PacketTransactor::port_lost(const std::string& reason) {
  return BusResult{BusStatus::BusDown, 0, {}, reason};
}

AnswerShape PacketTransactor::answer_shape(const Request& request) const {
  switch (request.reply) {
    case ReplyKind::None: break;
    case ReplyKind::Ack: return AnswerShape::of(0, {0});
    case ReplyKind::Data:
      // A refusal answers a read without its data; a fence takes only its data.
      return request.fence_units != 0 ? AnswerShape::of(0, {request.count}) : AnswerShape::of(0, {request.count, 0});
    case ReplyKind::Ping: {
      AnswerShape shape;
      for (std::size_t params = 0; params <= rules_.max_ping_params; ++params) shape.lengths.set(params);
      return shape;
    }
    case ReplyKind::SyncRead: return AnswerShape::of(0, {request.count});
  }
  return {};
}

// An adapter's echo of our own frame, in one place (the header's rule): a frame byte for byte the
// request may be the answer after all (a PING answered with ERROR 0x01 is), so the first one of
// an attempt is held back and taken at the deadline only if nothing else came and the line has
// never been seen to echo — to hand back a request it cannot answer, or our frame and then the
// answer.
class PacketTransactor::EchoRule {
 public:
  explicit EchoRule(bool& line_echoes) : line_echoes_(line_echoes) {}
  void next_attempt() { held_.reset(); }
  // A frame identical to the request, as judged: true when it is held back (nothing more to do
  // with it now).
  bool held_back(Packet& frame, Verdict verdict, bool first) {
    if (verdict == Verdict::NotOurs) line_echoes_ = true;  // it cannot be the answer: an echo
    if (verdict != Verdict::Answer || !first) return false;
    held_ = std::move(frame);
    return true;
  }
  // The answer came: true when a frame held back was only our echo (dropped).
  bool answer_came() {
    if (!held_) return false;
    held_.reset();
    line_echoes_ = true;  // our frame came back, then the answer
    return true;
  }
  // The attempt's wait is over without an answer: the frame held back, when it is the answer.
  std::optional<Packet> answer_at_deadline() {
    if (!held_ || line_echoes_) return std::nullopt;
    return std::exchange(held_, std::nullopt);
  }

 private:
  bool& line_echoes_;
  std::optional<Packet> held_;
};

// One execute(): the request's timing, its attempts as named steps (send, await the answer:
// read the line, judge each frame, wait out bytes in flight), and what the attempts learnt.
class PacketTransactor::Transaction {
 public:
  Transaction(PacketTransactor& line, const Request& request, TransactionEvents& events);
  BusResult run();

 private:
  // What one attempt has come to so far.
  struct Attempt {
    SteadyClock::time_point sent_at{};
    SteadyClock::time_point original_deadline{};
    SteadyClock::time_point deadline{};
    std::size_t frames = 0;
    bool quiet_wait = false;  // after a damaged answer: waiting for the line to go quiet
    bool heard = false;       // a frame other than our own echo, or a damaged one, came back
    bool send_again = false;  // our frame arrived damaged (d55d's checksum bit)
    std::optional<BusResult> outcome;
    std::optional<SteadyClock::time_point> last_rx;
    bool decided() const { return outcome || send_again; }
  };

  Expected<Ok> send();
  Expected<Ok> await_answer();
  Expected<Ok> read_line();
  void on_frame(Packet frame);
  bool note_if_late(const Packet& frame);
  void on_damaged(std::uint8_t id);
  void accept(Packet frame);
  bool wait_out_bytes_in_flight(SteadyClock::time_point now);

  PacketTransactor& line_;
  const Request& request_;
  TransactionEvents& events_;
  const std::chrono::nanoseconds request_time_;  // the request's wire time
  const std::chrono::nanoseconds reply_time_;    // the answer's wire time plus the reply allowance
  const std::chrono::nanoseconds timeout_;       // one attempt's wait
  const std::chrono::milliseconds write_timeout_;
  const AnswerShape shape_;  // every answer the request would take
  const bool anyone_;        // a rate scan's PING to the broadcast ID
  std::bitset<256> sync_expected_;
  std::bitset<256> sync_answered_;
  std::bitset<256> sync_ambiguous_;  // members owing late answers that look like this SYNC READ's
  AttemptFindings found_;
  unsigned made_ = 0;
  OwedAnswers::Tally tally_;
  EchoRule echo_;
  Attempt attempt_;
};

namespace {

std::size_t reply_bytes(const PacketRules& rules, ReplyKind reply, std::size_t count) {
  std::size_t bytes = protocol::kMinFrameSize;
  if (reply == ReplyKind::Data || reply == ReplyKind::SyncRead) bytes += count;
  if (reply == ReplyKind::Ping) bytes += rules.max_ping_params;
  return bytes;
}

}  // namespace

PacketTransactor::Transaction::Transaction(PacketTransactor& line, const Request& request, TransactionEvents& events)
    : line_(line),
      request_(request),
      events_(events),
      request_time_(wire_time(line.port_.settings(), request.frame.size())),
      reply_time_(wire_time(line.port_.settings(), reply_bytes(line.rules_, request.reply, request.count)) +
                  line.timing_.reply_allowance),
      timeout_(request_time_ + reply_time_),
      write_timeout_(std::chrono::ceil<std::chrono::milliseconds>(request_time_ + line.timing_.reply_allowance) + 50ms),
      shape_(line.answer_shape(request)),
      anyone_(request.reply == ReplyKind::Ping && broadcast(request)),
      // SYNC READ owes per silent member (run()); a broadcast PING's answers are anyone's.
      tally_(line.owed_, request.servo_id, shape_,
             request.reply != ReplyKind::None && request.reply != ReplyKind::SyncRead && !broadcast(request),
             request.fence_units),
      echo_(line.adapter_echoes_) {
  for (const auto id : request.sync_ids) {
    sync_expected_.set(id);
    // Its answer could not be told from a late one: it is read on its own (behind a fence).
    if (line.owed_.collides(id, shape_)) sync_ambiguous_.set(id);
  }
  found_.timeout = timeout_;
}

std::optional<BusResult> PacketTransactor::fence_before(const Request& request, TransactionEvents& events) {
  if (request.reply == ReplyKind::None || request.reply == ReplyKind::SyncRead || broadcast(request)) {
    return std::nullopt;
  }
  const AnswerShape shape = answer_shape(request);
  const auto fence_shape = [](unsigned units) { return AnswerShape::of(0, {units}); };
  // Each fence settles at least what came before the first owed fence of its length; a few are
  // enough for any list a servo can owe (transactor.h OwedAnswers).
  for (unsigned round = 0; owed_.collides(request.servo_id, shape); ++round) {
    const auto units = owed_.fence_length(request.servo_id, fence_shape, shape, kLongestFence);
    if (!units || round == kLongestFence) {
      // Not reachable with the fence lengths there are; said rather than looped on.
      spdlog::warn("{}servo {} owes {} late answers no fence can be told from: they are forgotten before {}",
                   timing_.label, request.servo_id, owed_.count(request.servo_id), describe(request));
      owed_.settled(request.servo_id);
      return std::nullopt;
    }
    Request fence = read_request(request.servo_id, {0, static_cast<std::uint16_t>(*units)}, request.attempts);
    fence.fence_units = *units;
    counters_.fences.fetch_add(1, std::memory_order_relaxed);
    BusResult fenced = Transaction(*this, fence, events).run();
    if (fenced.status == BusStatus::Ok) continue;
    if (fenced.status != BusStatus::BusDown) {
      fenced.detail += fmt::format(
          " (a fence before {}: servo {} still owes late answers that could look like its answer; it was not sent)",
          describe(request), request.servo_id);
    }
    return fenced;
  }
  return std::nullopt;
}

BusResult PacketTransactor::execute(const Request& request, TransactionEvents& events) {
  if (!port_.is_open()) return port_lost(port_.settings().device + " is not open");
  if (auto not_sent = fence_before(request, events)) return std::move(*not_sent);
  return Transaction(*this, request, events).run();
}

BusResult PacketTransactor::Transaction::run() {
  while (made_ < request_.attempts) {
    if (made_++ > 0) line_.counters_.retries.fetch_add(1, std::memory_order_relaxed);
    if (const auto sent = send(); !sent) return line_.port_lost(sent.error());
    if (request_.reply == ReplyKind::None) {
      // Broadcast or unanswered write: complete once it is on the wire.
      if (const auto drained = line_.port_.drain(); !drained) return line_.port_lost(drained.error());
      std::this_thread::sleep_until(attempt_.sent_at + request_time_);
      return BusResult{};
    }
    if (const auto waited = await_answer(); !waited) return line_.port_lost(waited.error());
    if (attempt_.outcome) return std::move(*attempt_.outcome);
    if (attempt_.send_again) continue;  // our frame arrived damaged: send it again now
    if (auto echo = echo_.answer_at_deadline()) {
      tally_.heard();
      accept(std::move(*echo));
      if (attempt_.outcome) return std::move(*attempt_.outcome);
    }
    if (request_.reply == ReplyKind::SyncRead) {
      // The silent are the engine's to follow up; their answers may still come.
      for (const auto id : request_.sync_ids) {
        if (!sync_answered_.test(id)) line_.owed_.add(id, shape_, 1, 0, attempt_.sent_at);
      }
      return BusResult{};
    }
    line_.counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
    events_.unanswered(request_.servo_id);
    if (anyone_ && attempt_.heard) break;  // colliding answers: someone is there
  }
  return line_.fail(request_, found_, made_);
}

// Drops what the input holds (stray), then transmits: an attempt begins. Answers owed to requests
// that gave up are recognised in what is dropped (a late servo is told apart from noise).
Expected<Ok> PacketTransactor::Transaction::send() {
  const auto stray = line_.port_.read_available(line_.rx_buffer_);
  if (!stray) return unexpected(stray.error());
  line_.decoder_.reset();
  if (*stray > 0) {
    line_.decoder_.feed(std::span<const std::uint8_t>(line_.rx_buffer_.data(), *stray));
    while (auto event = line_.decoder_.next()) {
      if (event->kind == protocol::DecodeEvent::Kind::Frame) note_if_late(event->packet);
    }
    line_.decoder_.reset();
    line_.decoder_discarded_seen_ = line_.decoder_.discarded_bytes();  // stray, not header hunting
  }
  const auto flushed = line_.port_.discard_input();
  if (!flushed) return unexpected(flushed.error());
  line_.stray_.count(*stray + *flushed, line_.timing_.label, [&] { return "before " + line_.describe(request_); });
  line_.count_discarded();

  if (spdlog::should_log(spdlog::level::trace)) {
    spdlog::trace("{}tx {}", line_.timing_.label, spdlog::to_hex(request_.frame));
  }
  const auto sent_at = SteadyClock::now();
  tally_.sent(sent_at);
  attempt_ = Attempt{};
  attempt_.sent_at = sent_at;
  attempt_.original_deadline = attempt_.deadline = sent_at + timeout_;
  echo_.next_attempt();
  if (const auto written = line_.port_.write_all(request_.frame, write_timeout_); !written) {
    return unexpected(written.error());
  }
  return Ok{};
}

// Reads and judges until the attempt is decided (an outcome, or send again) or its wait is over.
Expected<Ok> PacketTransactor::Transaction::await_answer() {
  for (;;) {
    const auto left = attempt_.deadline - SteadyClock::now();
    if (left > 0ns) {
      const auto readable = line_.port_.wait_readable(left);
      if (!readable) return unexpected(readable.error());
    }
    // Read what the port holds even after the deadline: when this thread ran late (a busy
    // machine), the answer may be waiting.
    if (auto read = read_line(); !read) return read;
    if (attempt_.decided()) return Ok{};
    const auto now = SteadyClock::now();
    if (now < attempt_.deadline) continue;
    if (!wait_out_bytes_in_flight(now)) return Ok{};
  }
}

// Everything the port holds, through the decoder, each event judged, until the attempt is decided.
Expected<Ok> PacketTransactor::Transaction::read_line() {
  for (;;) {
    const auto received = line_.port_.read_available(line_.rx_buffer_);
    if (!received) return unexpected(received.error());
    if (*received == 0) return Ok{};
    const std::span<const std::uint8_t> bytes(line_.rx_buffer_.data(), *received);
    if (spdlog::should_log(spdlog::level::trace)) spdlog::trace("{}rx {}", line_.timing_.label, spdlog::to_hex(bytes));
    attempt_.last_rx = SteadyClock::now();
    line_.decoder_.feed(bytes);
    // Bytes still arriving after a damaged answer: wait until the line is quiet.
    if (attempt_.quiet_wait) {
      attempt_.deadline = std::min(attempt_.original_deadline, SteadyClock::now() + line_.quiet_gap_);
    }
    while (!attempt_.decided()) {
      auto event = line_.decoder_.next();
      if (!event) break;
      if (event->kind == protocol::DecodeEvent::Kind::Frame) {
        on_frame(std::move(event->packet));
      } else {
        on_damaged(event->packet.id);
      }
    }
    line_.count_discarded();
    if (attempt_.decided()) return Ok{};
    // A short read emptied the tty's buffer: skip the read() that would say EAGAIN.
    if (*received < line_.rx_buffer_.size()) return Ok{};
  }
}

// Bytes still arriving at the deadline (an answer in flight, late or colliding): wait until the
// line is quiet, bounded by one more timeout, so a retry does not transmit into them. False: the
// attempt's wait is over.
bool PacketTransactor::Transaction::wait_out_bytes_in_flight(SteadyClock::time_point now) {
  const auto guard_end = attempt_.original_deadline + timeout_;
  if (!attempt_.last_rx || now >= *attempt_.last_rx + line_.quiet_gap_ || now >= guard_end) return false;
  attempt_.deadline = std::min(*attempt_.last_rx + line_.quiet_gap_, guard_end);
  return true;
}

// A valid frame: the answer, a refusal, our frame sent back, or somebody else's (not ours).
void PacketTransactor::Transaction::on_frame(Packet frame) {
  const bool owed =
      request_.reply != ReplyKind::SyncRead ||
      (sync_expected_.test(frame.id) && !sync_answered_.test(frame.id) && !sync_ambiguous_.test(frame.id));
  Verdict verdict =
      owed ? judge_reply(line_.rules_, request_.reply, request_.servo_id, request_.count, frame) : Verdict::NotOurs;
  // A fence is answered by its data alone: a refusal could be an owed answer's.
  if (request_.fence_units != 0 && verdict != Verdict::Answer) verdict = Verdict::NotOurs;
  const bool first = attempt_.frames++ == 0;
  const bool echo = frame == request_.packet;
  if (echo) {
    if (echo_.held_back(frame, verdict, first)) return;
  } else {
    attempt_.heard = true;
    // An answer still owed for an earlier request (to this servo or another) has come.
    if (verdict == Verdict::NotOurs) {
      if (note_if_late(frame) && frame.id == request_.servo_id && request_.reply != ReplyKind::SyncRead && !anyone_) {
        // Its own answer will be as late: waiting for it, and asking again, costs the bus.
        line_.counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
        attempt_.outcome =
            BusResult{BusStatus::Timeout,
                      0,
                      {},
                      fmt::format("{}servo {} answers late (later than {:.1f} ms): {} not asked again",
                                  line_.timing_.label, frame.id, to_ms(timeout_), line_.describe(request_))};
        return;
      }
    } else if (frame.id == request_.servo_id) {
      tally_.heard();
    }
  }
  switch (verdict) {
    case Verdict::NotOurs:
      line_.counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
      if (!echo) events_.foreign(frame.id);  // an adapter's echo of our request is nobody's answer
      if (spdlog::should_log(spdlog::level::debug)) {
        spdlog::debug("{}ignored a frame from ID {} (ERROR 0x{:02X}, {} bytes) while waiting for {}",
                      line_.timing_.label, frame.id, frame.code, frame.params.size(), line_.describe(request_));
      }
      return;
    case Verdict::Answer:
      if (echo_.answer_came()) line_.counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
      return accept(std::move(frame));
    case Verdict::Refused:
      line_.owed_.settled(frame.id);  // only this request's answer looks like this
      events_.answered(frame.id, frame.code);
      attempt_.outcome = BusResult{BusStatus::ServoRefused,
                                   frame.code,
                                   {},
                                   fmt::format("{}servo {} refused {} (ERROR 0x{:02X})", line_.timing_.label, frame.id,
                                               line_.describe(request_), frame.code)};
      return;
    case Verdict::RefusedDamaged:
      events_.answered(frame.id, frame.code);
      found_.refused_damaged = true;
      found_.last_error = frame.code;
      attempt_.send_again = true;
      return;
  }
}

// A frame that is nobody's answer now: when it is one its servo owed, the servo is told it came
// late. True when the engine gives up asking that servo (it answers late over and over).
bool PacketTransactor::Transaction::note_if_late(const Packet& frame) {
  const auto arrival = line_.owed_.arrived(frame.id, AnswerShape::frame(0, frame.params.size()));
  if (!arrival.late_since) return false;
  return events_.late(frame.id,
                      std::chrono::duration_cast<std::chrono::milliseconds>(SteadyClock::now() - *arrival.late_since));
}

// A damaged frame (checksum, or a LEN no frame can have).
void PacketTransactor::Transaction::on_damaged(std::uint8_t id) {
  line_.counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
  found_.damaged_any = true;
  attempt_.heard = true;
  events_.damaged();
  if (request_.reply == ReplyKind::SyncRead || id != request_.servo_id) return;
  // Not counted as this request's answer (tally_): it may have been an owed one, and this
  // request's answer may still come.
  if (!attempt_.quiet_wait) {
    // Our servo's answer arrived damaged: no valid one follows. Retry as soon as the line is
    // quiet (transmitting into the tail of a frame would collide).
    attempt_.quiet_wait = true;
    attempt_.deadline = std::min(attempt_.original_deadline, SteadyClock::now() + line_.quiet_gap_);
  }
}

void PacketTransactor::Transaction::accept(Packet frame) {
  line_.counters_.frames_ok.fetch_add(1, std::memory_order_relaxed);
  events_.answered(frame.id, frame.code);
  if (made_ == 1) events_.answered_in_time(frame.id);
  // Only this request's answer looks like this: whatever the servo owed before has come or never will.
  if (request_.fence_units != 0) {
    line_.owed_.fence_answered(frame.id, request_.fence_units);
  } else if (!anyone_) {
    line_.owed_.settled(frame.id);
  }
  if (request_.reply != ReplyKind::SyncRead) {
    attempt_.outcome = BusResult{BusStatus::Ok, frame.code, std::move(frame.params), {}};
    return;
  }
  sync_answered_.set(frame.id);
  events_.sync_answer(frame.id, frame.params);
  if (sync_answered_ == sync_expected_) {
    attempt_.outcome = BusResult{};
    return;
  }
  // The next servo in the list answers after this one (docs/PROTOCOL.md §1.1): restart the wait.
  attempt_.deadline = SteadyClock::now() + reply_time_;
}

BusResult PacketTransactor::fail(const Request& request, const AttemptFindings& last, unsigned attempts_made) const {
  const auto attempts = fmt::format("{} attempt{}", attempts_made, attempts_made == 1 ? "" : "s");
  if (last.refused_damaged) {
    return BusResult{BusStatus::ServoRefused,
                     last.last_error,
                     {},
                     fmt::format("{}servo {} reported our {} as damaged (ERROR 0x{:02X}) after {}", timing_.label,
                                 request.servo_id, describe(request), last.last_error, attempts)};
  }
  if (last.damaged_any) {
    return BusResult{BusStatus::Corrupt,
                     0,
                     {},
                     fmt::format("{}only damaged answers to {} after {} (checksum or framing errors)", timing_.label,
                                 describe(request), attempts)};
  }
  return BusResult{BusStatus::Timeout,
                   0,
                   {},
                   fmt::format("{}no answer to {} after {} of {:.1f} ms", timing_.label, describe(request), attempts,
                               to_ms(last.timeout))};
}

}  // namespace sms::gateway
