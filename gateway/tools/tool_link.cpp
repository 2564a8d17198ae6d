#include "gateway/tools/tool_link.h"

#include <algorithm>
#include <array>
#include <cstring>
#include <stdexcept>
#include <thread>

#include <fmt/format.h>

#include "gateway/bus/packet_transactor.h"
#include "gateway/bus/rtu_transactor.h"
#include "gateway/bus/serial_port.h"
#include "protocol/d55d.h"

namespace sms::gateway {

using namespace std::chrono_literals;
using modbus_map::TableId;
using protocol::BusProtocol;

namespace {

constexpr std::array<ToolProtocol, 3> kToolProtocols{{
    {BusProtocol::Feetech, TableId::Sts, 0, 253, protocol::kBroadcastId, 500us, true, std::nullopt},
    {BusProtocol::D55d, TableId::D55d, 0, 253, protocol::kBroadcastId, 8000us, true, protocol::d55d::kReset},
    {BusProtocol::ModbusRtu, TableId::Smsmb, 1, 247, 0, 500us, false, std::nullopt},
}};

SerialSettings serial_of(const LinkSettings& settings) {
  return SerialSettings{settings.device, settings.baud, settings.parity, settings.stop_bits};
}

// Replies are waited for the protocol's usual return delay plus the adapter latency; no message
// prefix: a tool's messages name the device and the ID themselves.
TransactionTiming tool_timing(const LinkSettings& link) {
  return TransactionTiming{tool_protocol(link.protocol).usual_return_delay + link.latency, ""};
}

// What a tool learns while a transaction runs, beyond its result: whether anything came back,
// and which other IDs answered (late answers, a servo that just took another ID).
class Heard final : public TransactionEvents {
 public:
  explicit Heard(std::uint8_t asked) : asked_(asked) {}
  void answered(std::uint8_t, std::optional<std::uint8_t>) override { anything = true; }
  void foreign(std::uint8_t id) override {
    anything = true;
    if (id != asked_) other_ids.push_back(id);
  }
  void damaged() override {
    anything = true;
    damaged_any = true;
  }

  bool anything = false;
  bool damaged_any = false;
  std::vector<std::uint8_t> other_ids;

 private:
  std::uint8_t asked_;
};

// The tools' line on the engine's transactors (transactor.h): the same framing, answer rules,
// retries and refusals as the gateway, one transaction at a time on the tool's thread.
//
// A retried request may be answered twice: the first attempt's answer comes late, is taken for
// the second's, and the second's then looks like the answer to whatever is asked next (packets
// carry no transaction number; a PING and a one-byte READ look alike). After a transaction that
// had to retry, the next one first waits out one more reply timeout; what arrived meanwhile is
// flushed before its request is written. Single-attempt exchanges (a scan) do not wait: a scan
// finds late answers by their ID instead (tool_scan.cpp).
template <BusTransactor Transactor>
class TransactorLink final : public ServoLink {
 public:
  using Factory = std::unique_ptr<Transactor> (*)(const LinkSettings&, BusCounters&);
  TransactorLink(LinkSettings settings, Factory make)
      : settings_(std::move(settings)), transactor_(make(settings_, counters_)) {}

  Expected<Ok> open() override { return transactor_->open(); }

  Expected<Ok> set_baud(std::uint32_t baud) override {
    settings_.baud = baud;
    auto changed = transactor_->set_baud(baud);
    if (!changed)
      return unexpected(fmt::format("cannot set {} to {} bit/s: {}", settings_.device, baud, changed.error()));
    return Ok{};
  }

  const LinkSettings& settings() const override { return settings_; }
  void set_attempts(unsigned attempts) override { settings_.attempts = std::max(attempts, 1U); }
  void set_latency(std::chrono::milliseconds latency) override {
    settings_.latency = latency;
    transactor_->set_reply_allowance(tool_timing(settings_).reply_allowance);
  }

  LinkAnswer ping(std::uint8_t id) override {
    return run(id, [&] { return transactor_->ping_request(id, settings_.attempts); });
  }

  LinkAnswer read(std::uint8_t id, std::uint16_t address, std::uint16_t count) override {
    return run(id, [&] { return transactor_->prepare(ReadOp{id, address, count}, settings_.attempts); });
  }

  LinkAnswer write(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> data) override {
    return run(id, [&] {
      return transactor_->prepare(WriteOp{id, address, Bytes(data.begin(), data.end())}, settings_.attempts);
    });
  }

  LinkAnswer instruction(std::uint8_t id, std::uint8_t code) override {
    if constexpr (requires(const Transactor& t) { t.instruction_request(id, code, 1U); }) {
      return run(id, [&] { return transactor_->instruction_request(id, code, settings_.attempts); });
    } else {
      LinkAnswer answer;
      answer.status = LinkStatus::PortError;
      answer.detail = fmt::format("instruction 0x{:02X} does not exist on a {} line", code,
                                  protocol::to_string(settings_.protocol));
      return answer;
    }
  }

  std::chrono::nanoseconds wire_time(std::size_t bytes) const override {
    return gateway::wire_time(serial_of(settings_), bytes);
  }

 private:
  template <typename MakeRequest>
  LinkAnswer run(std::uint8_t id, MakeRequest make_request) {
    const auto request = make_request();  // throws std::invalid_argument for what the protocol cannot say
    std::this_thread::sleep_until(quiet_until_);
    Heard heard(id);
    const auto retries_before = counters_.retries.load(std::memory_order_relaxed);
    const auto stray_before = counters_.stray_bytes.load(std::memory_order_relaxed);
    BusResult result = transactor_->execute(request, heard);
    if (counters_.retries.load(std::memory_order_relaxed) != retries_before) {
      quiet_until_ = std::chrono::steady_clock::now() + tool_reply_timeout(*this, 0, protocol::kMinFrameSize);
    }
    LinkAnswer answer;
    answer.data = std::move(result.data);
    answer.servo_status = result.servo_error;
    answer.heard_anything = heard.anything;
    answer.other_ids = std::move(heard.other_ids);
    answer.damaged = heard.damaged_any;
    answer.dropped_before = counters_.stray_bytes.load(std::memory_order_relaxed) - stray_before;
    answer.detail = std::move(result.detail);
    switch (result.status) {
      case BusStatus::Ok: answer.status = LinkStatus::Ok; break;
      // Frames came, none was the answer: say so rather than "no answer".
      case BusStatus::Timeout: answer.status = heard.anything ? LinkStatus::Corrupt : LinkStatus::Timeout; break;
      case BusStatus::Corrupt: answer.status = LinkStatus::Corrupt; break;
      case BusStatus::ServoRefused: answer.status = LinkStatus::Refused; break;
      default: answer.status = LinkStatus::PortError; break;
    }
    return answer;
  }

  LinkSettings settings_;
  BusCounters counters_;  // what the transactor counts; the link reads the retries
  std::unique_ptr<Transactor> transactor_;
  std::chrono::steady_clock::time_point quiet_until_{};
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
  if (settings.protocol == BusProtocol::ModbusRtu) {
    return std::make_unique<TransactorLink<RtuTransactor>>(settings, [](const LinkSettings& link,
                                                                        BusCounters& counters) {
      return std::make_unique<RtuTransactor>(RtuLineSettings{serial_of(link), link.rtu}, tool_timing(link), counters);
    });
  }
  return std::make_unique<TransactorLink<PacketTransactor>>(
      settings, [](const LinkSettings& link, BusCounters& counters) {
        return std::make_unique<PacketTransactor>(link.protocol, serial_of(link), tool_timing(link), counters);
      });
}

std::chrono::nanoseconds tool_reply_timeout(const ServoLink& link, std::size_t request_bytes, std::size_t reply_bytes) {
  const LinkSettings& settings = link.settings();
  return link.wire_time(request_bytes + reply_bytes) + tool_protocol(settings.protocol).usual_return_delay +
         settings.latency;
}

}  // namespace sms::gateway
