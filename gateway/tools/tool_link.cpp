#include "gateway/tools/tool_link.h"

#include <algorithm>
#include <array>
#include <cstring>
#include <stdexcept>
#include <thread>

#include <fmt/format.h>

#include "gateway/bus/packet_rules.h"
#include "gateway/bus/rtu_bus_engine.h"
#include "gateway/bus/serial_port.h"
#include "gateway/bus/serial_port_termios2.h"
#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"
#include "protocol/modbus_pdu.h"
#include "protocol/stream_decoder.h"

namespace sms::gateway {

using namespace std::chrono_literals;
using protocol::BusProtocol;
using modbus_map::TableId;

namespace {

constexpr std::array<ToolProtocol, 3> kToolProtocols{{
    {BusProtocol::Feetech, TableId::Sts, 0, 253, protocol::kBroadcastId, 500us, true},
    {BusProtocol::D55d, TableId::D55d, 0, 253, protocol::kBroadcastId, 8000us, true},
    {BusProtocol::ModbusRtu, TableId::Smsmb, 1, 247, 0, 500us, false},
}};

// A retried request may be answered twice: the first attempt's answer comes late, is taken for
// the second's, and the second's then looks like the answer to whatever is asked next (packets
// carry no transaction number; a PING and a one-byte READ look alike). After an exchange that
// had to retry, the next one first waits out one more reply timeout; what arrived meanwhile is
// flushed before its request is written. Single-attempt exchanges (a scan) do not wait: a scan
// finds late answers by their ID instead (tool_scan.cpp).
class QuietLine {
 public:
  class Exchange {
   public:
    Exchange(QuietLine& line, std::chrono::nanoseconds reply_timeout) : line_(line), reply_timeout_(reply_timeout) {
      std::this_thread::sleep_until(line_.quiet_until_);
    }
    ~Exchange() {
      if (retried_) line_.quiet_until_ = std::chrono::steady_clock::now() + reply_timeout_;
    }
    Exchange(const Exchange&) = delete;
    Exchange& operator=(const Exchange&) = delete;
    // An attempt got no answer, or a damaged or foreign one, and another attempt follows.
    void retrying() { retried_ = true; }

   private:
    QuietLine& line_;
    std::chrono::nanoseconds reply_timeout_;
    bool retried_ = false;
  };

 private:
  std::chrono::steady_clock::time_point quiet_until_{};
};

SerialSettings serial_of(const LinkSettings& settings) {
  return SerialSettings{settings.device, settings.baud, settings.parity, settings.stop_bits};
}

// ---- feetech / d55d ---------------------------------------------------------------------------

class PacketLink final : public ServoLink {
 public:
  explicit PacketLink(LinkSettings settings)
      : settings_(std::move(settings)),
        rules_(packet_rules(settings_.protocol)),
        port_(serial_of(settings_)),
        decoder_(*rules_.format) {}

  Expected<Ok> open() override { return port_.open(); }

  Expected<Ok> set_baud(std::uint32_t baud) override {
    settings_.baud = baud;
    if (!port_.is_open()) return Ok{};
    // On the open descriptor: a reopen can meet EBUSY while someone else holds the tty.
    if (const int error =
            detail::configure_raw_line(port_.native_handle(), baud, settings_.parity, settings_.stop_bits);
        error != 0) {
      return unexpected(fmt::format("cannot set {} to {} bit/s: {}", settings_.device, baud, std::strerror(error)));
    }
    return Ok{};
  }

  const LinkSettings& settings() const override { return settings_; }
  void set_attempts(unsigned attempts) override { settings_.attempts = std::max(attempts, 1U); }
  void set_latency(std::chrono::milliseconds latency) override { settings_.latency = latency; }

  LinkAnswer ping(std::uint8_t id) override { return exchange(protocol::ping(id), Expect::Ping, 1); }

  LinkAnswer read(std::uint8_t id, std::uint16_t address, std::uint16_t count) override {
    if (address > 0xFF || count == 0 || count > protocol::kMaxParams || address + count > 0x100) {
      throw std::invalid_argument(fmt::format("READ of {} bytes at {}: packet tables are bytes 0-255", count, address));
    }
    return exchange(protocol::read(id, static_cast<std::uint8_t>(address), static_cast<std::uint8_t>(count)),
                    Expect::Read, count);
  }

  LinkAnswer write(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> data) override {
    if (address > 0xFF || data.empty() || address + data.size() > 0x100) {
      throw std::invalid_argument(fmt::format("WRITE of {} bytes at {}: packet tables are bytes 0-255", data.size(),
                                              address));
    }
    return exchange(protocol::write(id, static_cast<std::uint8_t>(address), data), Expect::Write, 0);
  }

  std::chrono::nanoseconds wire_time(std::size_t bytes) const override {
    return gateway::wire_time(serial_of(settings_), bytes);
  }

 private:
  enum class Expect : std::uint8_t { Ping, Read, Write };

  LinkAnswer exchange(const protocol::Packet& request, Expect expect, std::size_t reply_params) {
    const Bytes frame = protocol::encode(*rules_.format, request);
    const bool broadcast = request.id == protocol::kBroadcastId;
    const auto timeout = tool_reply_timeout(*this, frame.size(), protocol::kMinFrameSize + reply_params);
    QuietLine::Exchange quiet(quiet_, timeout);
    LinkAnswer answer;
    bool corrupt = false;
    bool refused_damaged = false;  // an answer said our frame arrived damaged (d55d checksum bit)
    const ReplyKind kind = expect == Expect::Ping ? ReplyKind::Ping : expect == Expect::Read ? ReplyKind::Data : ReplyKind::Ack;
    // Nothing answers a broadcast WRITE: never sent twice. A broadcast PING may be repeated.
    const unsigned attempts = broadcast && expect != Expect::Ping ? 1 : settings_.attempts;
    for (unsigned attempt = 0; attempt < attempts; ++attempt) {
      if (auto flushed = port_.discard_input(); !flushed) return port_error(flushed.error());
      decoder_.reset();
      if (auto written = port_.write_all(frame, 100ms); !written) return port_error(written.error());
      if (broadcast && expect != Expect::Ping) {
        // Nobody answers: done once the frame is on the wire and the servos had a moment.
        std::this_thread::sleep_for(wire_time(frame.size()) + settings_.latency);
        answer.status = LinkStatus::Ok;
        return answer;
      }
      const auto deadline = std::chrono::steady_clock::now() + timeout;
      bool send_again = false;
      while (!send_again) {
        const auto left = deadline - std::chrono::steady_clock::now();
        if (left <= 0ns) break;
        auto readable = port_.wait_readable(left);
        if (!readable) return port_error(readable.error());
        if (!*readable) break;
        std::array<std::uint8_t, 512> buffer{};
        auto got = port_.read_available(buffer);
        if (!got) return port_error(got.error());
        if (*got == 0) continue;
        answer.heard_anything = true;
        decoder_.feed(std::span(buffer).first(*got));
        while (const auto event = decoder_.next()) {
          if (event->kind != protocol::DecodeEvent::Kind::Frame) {
            corrupt = true;
            answer.damaged = true;
            continue;
          }
          const protocol::Packet& reply = event->packet;
          if (reply == request) continue;  // the adapter's echo of our own frame
          if (broadcast) {
            // Broadcast PING: some servo is there at this rate.
            answer.status = LinkStatus::Ok;
            return answer;
          }
          if (reply.id != request.id) {
            corrupt = true;  // a late answer, or a servo that just took another ID
            answer.other_ids.push_back(reply.id);
            continue;
          }
          answer.servo_status = reply.code;
          // The engine's rule (packet_rules.h): refusals, d55d's "arrived damaged", PING shapes.
          switch (judge_reply(rules_, kind, request.id, reply_params, reply)) {
            case Verdict::Answer:
              answer.status = LinkStatus::Ok;
              answer.data = reply.params;
              return answer;
            case Verdict::Refused:
              return refused(std::move(answer), expect == Expect::Read ? "READ" : expect == Expect::Write ? "WRITE" : "PING");
            case Verdict::RefusedDamaged:
              refused_damaged = true;  // our frame arrived damaged: send it again now
              send_again = true;
              break;
            case Verdict::NotOurs:
              corrupt = true;
              break;
          }
          if (send_again) break;
        }
      }
      if (broadcast && answer.heard_anything) break;  // colliding answers: someone is there
      if (attempt + 1 < attempts) quiet.retrying();
    }
    if (refused_damaged) {
      answer.detail = fmt::format("the servo said our frame arrived damaged (ERROR byte 0x{:02X}); {} attempt{} sent",
                                  answer.servo_status, attempts, attempts == 1 ? "" : "s");
      answer.status = LinkStatus::Refused;
      return answer;
    }
    answer.status = corrupt ? LinkStatus::Corrupt : LinkStatus::Timeout;
    answer.detail = fmt::format("{} from ID {} at {} bit/s ({} attempt{})",
                                corrupt ? "only damaged or foreign frames" : "no answer", request.id, settings_.baud,
                                attempts, attempts == 1 ? "" : "s");
    return answer;
  }

  LinkAnswer refused(LinkAnswer answer, std::string_view what) const {
    answer.status = LinkStatus::Refused;
    answer.detail = fmt::format("the servo refused the {} (ERROR byte 0x{:02X})", what, answer.servo_status);
    return answer;
  }

  static LinkAnswer port_error(const std::string& detail) {
    LinkAnswer answer;
    answer.status = LinkStatus::PortError;
    answer.detail = detail;
    return answer;
  }

  QuietLine quiet_;
  LinkSettings settings_;
  const PacketRules& rules_;
  SerialPort port_;
  protocol::StreamDecoder decoder_;
};

// ---- modbus-rtu -------------------------------------------------------------------------------

namespace fc = protocol::function_code;

class ModbusLink final : public ServoLink {
 public:
  explicit ModbusLink(LinkSettings settings) : settings_(std::move(settings)), master_(make_master()) {}

  Expected<Ok> open() override { return master_->open(); }

  Expected<Ok> set_baud(std::uint32_t baud) override {
    const bool was_open = master_->is_open();
    master_->close();
    settings_.baud = baud;
    master_ = make_master();
    if (!was_open) return Ok{};
    return master_->open();
  }

  const LinkSettings& settings() const override { return settings_; }
  void set_attempts(unsigned attempts) override { settings_.attempts = std::max(attempts, 1U); }
  void set_latency(std::chrono::milliseconds latency) override { settings_.latency = latency; }

  LinkAnswer ping(std::uint8_t id) override {
    // Any answer, an exception too, says a slave is there.
    return exchange(id, read_pdu(0, 1), 0, true);
  }

  LinkAnswer read(std::uint8_t id, std::uint16_t address, std::uint16_t count) override {
    if (count == 0 || count > 125) throw std::invalid_argument(fmt::format("FC03 of {} registers: 1-125", count));
    return exchange(id, read_pdu(address, count), count, false);
  }

  LinkAnswer write(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> data) override {
    const std::size_t registers = data.size() / 2;
    if (data.size() % 2 != 0 || registers == 0 || registers > 123) {
      throw std::invalid_argument(fmt::format("a Modbus write carries 1-123 registers, not {} bytes", data.size()));
    }
    const auto hi = static_cast<std::uint8_t>(address >> 8);
    const auto lo = static_cast<std::uint8_t>(address);
    Bytes pdu = registers == 1
                    ? Bytes{fc::kWriteSingleRegister, hi, lo, data[0], data[1]}
                    : Bytes{fc::kWriteMultipleRegisters, hi, lo, 0, static_cast<std::uint8_t>(registers),
                            static_cast<std::uint8_t>(data.size())};
    if (registers > 1) pdu.insert(pdu.end(), data.begin(), data.end());
    return exchange(id, pdu, 0, false);
  }

  std::chrono::nanoseconds wire_time(std::size_t bytes) const override {
    return gateway::wire_time(serial_of(settings_), bytes);
  }

 private:
  std::unique_ptr<RtuMaster> make_master() const {
    return std::make_unique<RtuMaster>(RtuLineSettings{serial_of(settings_), settings_.rtu});
  }

  static Bytes read_pdu(std::uint16_t address, std::uint16_t count) {
    return {fc::kReadHoldingRegisters, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
            static_cast<std::uint8_t>(count >> 8), static_cast<std::uint8_t>(count)};
  }

  // `registers` > 0: an FC03 answer of that many registers; 0: a write echo (checked loosely:
  // the function code) or a PING.
  LinkAnswer exchange(std::uint8_t id, const Bytes& pdu, std::uint16_t registers, bool exception_is_answer) {
    LinkAnswer answer;
    const std::size_t reply_bytes = registers > 0 ? 5 + 2 * std::size_t{registers} : 8;
    // RtuMaster counts the reply timeout from when the request has left: no request bytes here.
    const auto timeout = tool_reply_timeout(*this, 0, reply_bytes);
    if (id == 0) {
      const RtuExchange sent = master_->send_only(0, pdu, timeout);
      answer.status = sent.outcome == RtuOutcome::Sent ? LinkStatus::Ok : LinkStatus::PortError;
      answer.detail = sent.detail;
      return answer;
    }
    QuietLine::Exchange quiet(quiet_, timeout);
    bool corrupt = false;
    std::string last;
    for (unsigned attempt = 0; attempt < settings_.attempts; ++attempt) {
      if (attempt > 0) quiet.retrying();  // the attempt before went unanswered, or wrongly
      RtuExchange exchange = master_->transact(id, pdu, timeout);
      switch (exchange.outcome) {
        case RtuOutcome::Reply: {
          answer.heard_anything = true;
          const Bytes& reply = exchange.pdu;
          if (reply.size() == 2 && reply[0] == (pdu[0] | fc::kExceptionBit)) {
            answer.servo_status = reply[1];
            if (exception_is_answer) {
              answer.status = LinkStatus::Ok;
              return answer;
            }
            answer.status = LinkStatus::Refused;
            answer.detail = fmt::format("slave {} answered exception 0x{:02X}", id, reply[1]);
            return answer;
          }
          if (reply.empty() || reply[0] != pdu[0]) {
            corrupt = true;
            last = "answer to another function";
            continue;
          }
          if (registers > 0) {
            if (reply.size() != 2 + 2 * std::size_t{registers} || reply[1] != 2 * registers) {
              corrupt = true;
              last = "register count differs from the request";
              continue;
            }
            answer.data.assign(reply.begin() + 2, reply.end());
          }
          answer.status = LinkStatus::Ok;
          return answer;
        }
        case RtuOutcome::Timeout:
          last = exchange.detail;
          break;
        case RtuOutcome::Corrupt:
        case RtuOutcome::WrongSlave:
          answer.heard_anything = true;
          corrupt = true;
          last = exchange.detail;
          if (exchange.other_slave) {
            answer.other_ids.push_back(*exchange.other_slave);
          } else {
            answer.damaged = true;
          }
          break;
        case RtuOutcome::PortError:
          answer.status = LinkStatus::PortError;
          answer.detail = exchange.detail;
          return answer;
        case RtuOutcome::Sent:
          break;
      }
    }
    answer.status = corrupt ? LinkStatus::Corrupt : LinkStatus::Timeout;
    answer.detail = fmt::format("{} from slave {} at {} bit/s ({} attempt{}): {}",
                                corrupt ? "only damaged or foreign frames" : "no answer", id, settings_.baud,
                                settings_.attempts, settings_.attempts == 1 ? "" : "s", last);
    return answer;
  }

  QuietLine quiet_;
  LinkSettings settings_;
  std::unique_ptr<RtuMaster> master_;
};

}  // namespace

const ToolProtocol& tool_protocol(BusProtocol protocol) {
  for (const auto& entry : kToolProtocols) {
    if (entry.protocol == protocol) return entry;
  }
  throw std::invalid_argument("no tool support for " + std::string(protocol::to_string(protocol)));
}

std::string_view to_string(LinkStatus status) {
  switch (status) {
    case LinkStatus::Ok: return "ok";
    case LinkStatus::Timeout: return "timeout";
    case LinkStatus::Corrupt: return "corrupt";
    case LinkStatus::Refused: return "refused";
    case LinkStatus::PortError: return "port error";
  }
  return "?";
}

std::unique_ptr<ServoLink> make_servo_link(const LinkSettings& settings) {
  if (settings.protocol == BusProtocol::ModbusRtu) return std::make_unique<ModbusLink>(settings);
  return std::make_unique<PacketLink>(settings);
}

std::chrono::nanoseconds tool_reply_timeout(const ServoLink& link, std::size_t request_bytes, std::size_t reply_bytes) {
  const LinkSettings& settings = link.settings();
  return link.wire_time(request_bytes + reply_bytes) + tool_protocol(settings.protocol).usual_return_delay +
         settings.latency;
}

}  // namespace sms::gateway
