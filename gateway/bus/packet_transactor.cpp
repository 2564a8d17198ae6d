#include "gateway/bus/packet_transactor.h"

#include <fmt/format.h>
#include <spdlog/fmt/bin_to_hex.h>
#include <spdlog/spdlog.h>

#include <bitset>
#include <stdexcept>
#include <thread>
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
    return fmt::format("poll block {}+{} cannot be read in one READ (byte addresses 0-255, 1-253 bytes)",
                       block.address, block.count);
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
    if (write->address > 0xFF) throw refuse("WRITE address " + std::to_string(write->address) + " is not a byte address");
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
      return fmt::format("{} at {} ({} bytes) to servo {}", name, params.at(0), params.size() - 1, request.servo_id);
    case ReplyKind::Ping:
      if (broadcast(request)) return fmt::format("broadcast {}", name);
      return fmt::format("{} of servo {}", name, request.servo_id);
    case ReplyKind::SyncRead:
      return fmt::format("{} {}+{} of servos {}", name, params.at(0), params.at(1), join_ids(request.sync_ids));
    case ReplyKind::None:
      break;
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

std::optional<SteadyClock::time_point> PacketTransactor::owed_until(const Request& request,
                                                                    SteadyClock::time_point now) const {
  std::optional<SteadyClock::time_point> latest;
  const auto consider = [&](std::uint8_t id) {
    if (owed_.owes(id, now) && (!latest || owed_.until(id) > *latest)) latest = owed_.until(id);
  };
  if (request.reply == ReplyKind::None) return latest;  // nothing awaited: nothing to mistake
  if (request.reply == ReplyKind::SyncRead) {
    for (const auto id : request.sync_ids) consider(id);
  } else if (broadcast(request)) {
    for (unsigned id = 0; id < protocol::kBroadcastId; ++id) consider(static_cast<std::uint8_t>(id));
  } else {
    consider(request.servo_id);
  }
  return latest;
}

Expected<Ok> PacketTransactor::settle(const Request& request) {
  auto now = SteadyClock::now();
  auto until = owed_until(request, now);
  if (!until) return Ok{};
  protocol::StreamDecoder watch(*rules_.format);
  std::size_t dropped = 0;
  while (until) {
    const auto readable = port_.wait_readable(*until - now);
    if (!readable) return unexpected(readable.error());
    for (;;) {
      const auto received = port_.read_available(rx_buffer_);
      if (!received) return unexpected(received.error());
      if (*received == 0) break;
      const std::span<const std::uint8_t> bytes(rx_buffer_.data(), *received);
      if (spdlog::should_log(spdlog::level::trace)) spdlog::trace("{}rx (late) {}", timing_.label, spdlog::to_hex(bytes));
      dropped += bytes.size();
      watch.feed(bytes);
      while (const auto event = watch.next()) {
        if (event->kind != protocol::DecodeEvent::Kind::Frame) continue;
        owed_.arrived(event->packet.id);
        counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
      }
      if (*received < rx_buffer_.size()) break;
    }
    now = SteadyClock::now();
    until = owed_until(request, now);
  }
  stray_.count(dropped, timing_.label, [&] { return "while waiting for owed late answers before " + describe(request); });
  return Ok{};
}

BusResult PacketTransactor::execute(const Request& request, TransactionEvents& events) {
  if (!port_.is_open()) return port_lost(port_.settings().device + " is not open");
  const SerialSettings& serial = port_.settings();
  const bool anyone = request.reply == ReplyKind::Ping && broadcast(request);  // a rate scan's PING
  std::bitset<256> sync_expected;
  std::bitset<256> sync_answered;
  for (const auto id : request.sync_ids) sync_expected.set(id);
  std::size_t reply_bytes = protocol::kMinFrameSize;
  if (request.reply == ReplyKind::Data || request.reply == ReplyKind::SyncRead) reply_bytes += request.count;
  if (request.reply == ReplyKind::Ping) reply_bytes += rules_.max_ping_params;
  const auto request_time = wire_time(serial, request.frame.size());
  const auto reply_time = wire_time(serial, reply_bytes) + timing_.reply_allowance;
  const auto write_timeout =
      std::chrono::ceil<std::chrono::milliseconds>(request_time + timing_.reply_allowance) + 50ms;

  AttemptFindings summary;
  summary.timeout = request_time + reply_time;
  if (const auto settled = settle(request); !settled) return port_lost(settled.error());
  unsigned made = 0;
  const auto late_window = kLateAnswerWindowAttempts * summary.timeout;
  // SYNC READ owes per silent member (below); a broadcast PING's answers are anyone's.
  const bool unicast_answer =
      request.reply != ReplyKind::None && request.reply != ReplyKind::SyncRead && !broadcast(request);
  OwedAnswers::Tally tally(owed_, request.servo_id, late_window, unicast_answer);
  while (made < request.attempts) {
    if (made++ > 0) counters_.retries.fetch_add(1, std::memory_order_relaxed);
    const auto flushed = port_.discard_input();
    if (!flushed) return port_lost(flushed.error());
    stray_.count(*flushed, timing_.label, [&] { return "before " + describe(request); });
    decoder_.reset();
    count_discarded();

    if (spdlog::should_log(spdlog::level::trace)) {
      spdlog::trace("{}tx {}", timing_.label, spdlog::to_hex(request.frame));
    }
    const auto sent_at = SteadyClock::now();
    tally.sent(sent_at);
    if (const auto written = port_.write_all(request.frame, write_timeout); !written) return port_lost(written.error());
    if (request.reply == ReplyKind::None) {
      // Broadcast or unanswered write: complete once it is on the wire.
      if (const auto drained = port_.drain(); !drained) return port_lost(drained.error());
      std::this_thread::sleep_until(sent_at + request_time);
      return BusResult{};
    }

    const auto original_deadline = sent_at + summary.timeout;
    auto deadline = original_deadline;
    std::size_t frames = 0;
    bool quiet_wait = false;  // after a damaged answer: waiting for the line to go quiet
    bool heard = false;  // a frame other than our own echo, or a damaged one, came back
    std::optional<Packet> echo_candidate;
    std::optional<BusResult> outcome;
    bool send_again = false;
    std::optional<SteadyClock::time_point> last_rx;

    const auto accept = [&](Packet frame) {
      counters_.frames_ok.fetch_add(1, std::memory_order_relaxed);
      events.answered(frame.id, frame.code);
      if (request.reply != ReplyKind::SyncRead) {
        outcome = BusResult{BusStatus::Ok, frame.code, std::move(frame.params), {}};
        return;
      }
      sync_answered.set(frame.id);
      events.sync_answer(frame.id, frame.params);
      if (sync_answered == sync_expected) {
        outcome = BusResult{};
        return;
      }
      // The next servo in the list answers after this one (docs/PROTOCOL.md §1.1): restart the wait.
      deadline = SteadyClock::now() + reply_time;
    };
    const auto handle_frame = [&](Packet frame) {
      const bool owed = request.reply != ReplyKind::SyncRead ||
                        (sync_expected.test(frame.id) && !sync_answered.test(frame.id));
      const Verdict verdict =
          owed ? judge_reply(rules_, request.reply, request.servo_id, request.count, frame) : Verdict::NotOurs;
      const bool echo = frame == request.packet;
      if (!echo) heard = true;
      // An answer still owed for an earlier request (to this servo or another) has come.
      if (verdict == Verdict::NotOurs && !echo) owed_.arrived(frame.id);
      if (verdict != Verdict::NotOurs && frame.id == request.servo_id && !echo) tally.heard();
      const bool first = frames++ == 0;
      // A frame identical to our request that cannot be its answer: this adapter echoes.
      if (echo && verdict == Verdict::NotOurs) adapter_echoes_ = true;
      if (verdict == Verdict::Answer && first && echo) {
        // Byte for byte our request: an adapter echoing what we sent. Hold it; it is the answer
        // only if nothing else comes before the deadline.
        echo_candidate = std::move(frame);
        return;
      }
      switch (verdict) {
        case Verdict::NotOurs:
          counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
          if (!echo) events.foreign(frame.id);  // an adapter's echo of our request is nobody's answer
          if (spdlog::should_log(spdlog::level::debug)) {
            spdlog::debug("{}ignored a frame from ID {} (ERROR 0x{:02X}, {} bytes) while waiting for {}", timing_.label,
                          frame.id, frame.code, frame.params.size(), describe(request));
          }
          return;
        case Verdict::Answer:
          if (echo_candidate) {
            counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
            echo_candidate.reset();
            adapter_echoes_ = true;  // our frame came back, then the answer
          }
          return accept(std::move(frame));
        case Verdict::Refused:
          events.answered(frame.id, frame.code);
          outcome = BusResult{BusStatus::ServoRefused, frame.code, {},
                              fmt::format("{}servo {} refused {} (ERROR 0x{:02X})", timing_.label, frame.id,
                                          describe(request), frame.code)};
          return;
        case Verdict::RefusedDamaged:
          events.answered(frame.id, frame.code);
          summary.refused_damaged = true;
          summary.last_error = frame.code;
          send_again = true;
          return;
      }
    };

    for (;;) {
      const auto left = deadline - SteadyClock::now();
      if (left > 0ns) {
        const auto readable = port_.wait_readable(left);
        if (!readable) return port_lost(readable.error());
      }
      // Read what the port holds even after the deadline: when this thread ran late (a busy
      // machine), the answer may be waiting.
      for (;;) {
        const auto received = port_.read_available(rx_buffer_);
        if (!received) return port_lost(received.error());
        if (*received == 0) break;
        const std::span<const std::uint8_t> bytes(rx_buffer_.data(), *received);
        if (spdlog::should_log(spdlog::level::trace)) spdlog::trace("{}rx {}", timing_.label, spdlog::to_hex(bytes));
        last_rx = SteadyClock::now();
        decoder_.feed(bytes);
        // Bytes still arriving after a damaged answer: wait until the line is quiet.
        if (quiet_wait) deadline = std::min(original_deadline, SteadyClock::now() + quiet_gap_);
        while (!outcome && !send_again) {
          auto event = decoder_.next();
          if (!event) break;
          if (event->kind == protocol::DecodeEvent::Kind::Frame) {
            handle_frame(std::move(event->packet));
            continue;
          }
          // A damaged frame (checksum, or a LEN no frame can have).
          counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
          summary.damaged_any = true;
          heard = true;
          events.damaged();
          if (request.reply != ReplyKind::SyncRead && event->packet.id == request.servo_id) tally.heard();
          if (request.reply != ReplyKind::SyncRead && event->packet.id == request.servo_id && !quiet_wait) {
            // Our servo's answer arrived damaged: no valid one follows. Retry as soon as the
            // line is quiet (transmitting into the tail of a frame would collide).
            quiet_wait = true;
            deadline = std::min(original_deadline, SteadyClock::now() + quiet_gap_);
          }
        }
        count_discarded();
        if (outcome || send_again) break;
        // A short read emptied the tty's buffer: skip the read() that would say EAGAIN.
        if (*received < rx_buffer_.size()) break;
      }
      if (outcome || send_again) break;
      const auto now = SteadyClock::now();
      if (now < deadline) continue;
      // Bytes still arriving at the deadline (an answer in flight, late or colliding): wait until
      // the line is quiet, bounded by one more timeout, so a retry does not transmit into them.
      const auto guard_end = original_deadline + summary.timeout;
      if (last_rx && now < *last_rx + quiet_gap_ && now < guard_end) {
        deadline = std::min(*last_rx + quiet_gap_, guard_end);
        continue;
      }
      break;
    }
    if (outcome) return std::move(*outcome);
    if (send_again) continue;  // our frame arrived damaged: send it again now
    if (echo_candidate && !adapter_echoes_) {
      // What looked like our own echo was the only frame, and this adapter has never echoed:
      // it was the answer after all (a PING answered with ERROR 0x01 is byte for byte the
      // request).
      tally.heard();
      accept(std::move(*echo_candidate));
      if (outcome) return std::move(*outcome);
    }
    if (request.reply == ReplyKind::SyncRead) {
      // The silent are the engine's to follow up; their answers may still come.
      for (const auto id : request.sync_ids) {
        if (!sync_answered.test(id)) owed_.add(id, 1, tally.last_sent() + late_window);
      }
      return BusResult{};
    }
    counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
    events.unanswered(request.servo_id);
    if (anyone && heard) break;  // colliding answers: someone is there
  }
  return fail(request, summary, made);
}

BusResult PacketTransactor::fail(const Request& request, const AttemptFindings& last, unsigned attempts_made) const {
  const auto attempts = fmt::format("{} attempt{}", attempts_made, attempts_made == 1 ? "" : "s");
  if (last.refused_damaged) {
    return BusResult{BusStatus::ServoRefused, last.last_error, {},
                     fmt::format("{}servo {} reported our {} as damaged (ERROR 0x{:02X}) after {}", timing_.label,
                                 request.servo_id, describe(request), last.last_error, attempts)};
  }
  if (last.damaged_any) {
    return BusResult{BusStatus::Corrupt, 0, {},
                     fmt::format("{}only damaged answers to {} after {} (checksum or framing errors)", timing_.label,
                                 describe(request), attempts)};
  }
  return BusResult{BusStatus::Timeout, 0, {},
                   fmt::format("{}no answer to {} after {} of {:.1f} ms", timing_.label, describe(request), attempts,
                               to_ms(last.timeout))};
}

}  // namespace sms::gateway
