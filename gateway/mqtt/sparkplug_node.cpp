// The Sparkplug node as one more Modbus client of the unit router: its requests, their answers,
// and the node's face (sparkplug_node.h). The other concerns are in sparkplug_*.cpp.
#include "gateway/mqtt/sparkplug_node_impl.h"

#include <cstdio>
#include <filesystem>

namespace sms::gateway {

std::string SparkplugNode::Impl::Answer::error_text() const {
  if (pdu.size() < 2) return "no answer";
  char code[8];
  std::snprintf(code, sizeof code, "0x%02X", pdu[1]);
  const std::string text = "exception " + std::string(code) + " (" +
                           std::string(modbus_map::to_string(static_cast<modbus_map::ModbusException>(pdu[1]))) + ")";
  return refusal.empty() ? text : text + ": " + refusal;
}

std::vector<std::uint16_t> SparkplugNode::Impl::Answer::registers() const {
  std::vector<std::uint16_t> values;
  for (std::size_t i = 2; i + 1 < pdu.size(); i += 2)
    values.push_back(static_cast<std::uint16_t>(pdu[i] << 8 | pdu[i + 1]));
  return values;
}

bool SparkplugNode::Impl::Answer::bit(std::size_t index) const {
  const std::size_t byte = 2 + index / 8;
  return byte < pdu.size() && ((pdu[byte] >> (index % 8)) & 1) != 0;
}

std::uint64_t SparkplugNode::Impl::epoch_ms() {
  return static_cast<std::uint64_t>(
      std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
          .count());
}

SparkplugNode::Impl::Impl(const config::Config& config, asio::io_context& io, UnitRouter& router,
                          const RolePolicy& policy)
    : config_(config),
      settings_(*config.mqtt),
      io_(io),
      router_(router),
      gate_(policy, "mqtt: the Sparkplug host"),
      timer_(io) {
  for (const auto& servo : config.servos) {
    if (servo.passthrough() || servo.view_of) continue;  // a servo is one device, however many units show it
    const ServoUnit* unit = router.servo_unit(servo.unit_id);
    if (unit == nullptr) continue;
    devices_.push_back(make_device(servo, *unit));
  }
  for (std::size_t i = 0; i < config.buses.size(); ++i) {
    heartbeats_.push_back(std::string(metric_name::kHeartbeatPrefix) + config.buses[i].name);
    heartbeat_values_.push_back(0);
  }
  if (const std::string dir = config::effective_state_dir(config); !dir.empty()) {
    bd_seq_path_ = (std::filesystem::path(dir) / kBdSeqFile).string();
  }
}

SparkplugStats SparkplugNode::Impl::stats() const {
  std::lock_guard lock(stats_mutex_);
  SparkplugStats copy = stats_;
  if (link_) copy.link = link_->stats();
  copy.devices = devices_.size();
  return copy;
}

// The router's answer to request `serial` (io thread), through Replies.
void SparkplugNode::Impl::deliver(std::uint64_t serial, Bytes response_pdu) {
  const auto it = pending_.find(serial);
  if (it == pending_.end()) return;
  auto done = std::move(it->second);
  pending_.erase(it);
  done(Answer{std::move(response_pdu), {}});
}

// Commands pass the role gate first; the node's own reads (what it publishes) do not: the
// role says what the hosts may change, not what the node reports.
void SparkplugNode::Impl::ask(std::uint8_t unit_id, const Request& request, std::function<void(const Answer&)> done) {
  const Bytes pdu = request_pdu(request);
  const bool command =
      !std::holds_alternative<ReadBitsRequest>(request) && !std::holds_alternative<ReadRegistersRequest>(request);
  if (const auto refusal = command ? gate_.check(settings_.role, unit_id, pdu) : std::nullopt) {
    return done(Answer{refusal->answer(pdu), refusal->text()});
  }
  const std::uint64_t serial = next_serial_++;
  pending_.emplace(serial, std::move(done));
  static const auto origin = std::make_shared<const std::string>("the Sparkplug host (NCMD/DCMD)");
  router_.handle(unit_id, pdu, Reply(replies_, serial, origin));
}

// Runs `reads` one after the other; `done` gets their answers (stops at the first failure).
void SparkplugNode::Impl::read_all(std::uint8_t unit_id, std::vector<ReadRegistersRequest> reads,
                                   std::vector<Answer> answers, std::function<void(std::vector<Answer>)> done) {
  if (answers.size() == reads.size() || (!answers.empty() && !answers.back().ok())) return done(std::move(answers));
  const ReadRegistersRequest next = reads[answers.size()];
  ask(unit_id, next,
      [this, unit_id, reads = std::move(reads), answers = std::move(answers),
       done = std::move(done)](const Answer& answer) mutable {
        answers.push_back(answer);
        read_all(unit_id, std::move(reads), std::move(answers), std::move(done));
      });
}

SparkplugNode::SparkplugNode(const config::Config& config, asio::io_context& io, UnitRouter& router,
                             const RolePolicy& policy)
    : impl_(std::make_shared<Impl>(config, io, router, policy)) {}
SparkplugNode::~SparkplugNode() { impl_->stop(); }
void SparkplugNode::start() { impl_->start(); }
void SparkplugNode::stop() { impl_->stop(); }
SparkplugStats SparkplugNode::stats() const { return impl_->stats(); }

}  // namespace sms::gateway
