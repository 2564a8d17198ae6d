#include "gateway/mqtt/sparkplug_node.h"

#include <algorithm>
#include <atomic>
#include <charconv>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <stdexcept>
#include <unordered_map>

#include <spdlog/spdlog.h>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/service/access_gate.h"
#include "gateway/service/modbus_request.h"
#include "gateway/units/gateway_unit.h"
#include "gateway/units/state_file.h"
#include "gateway/units/unit_router.h"

namespace sms::gateway {

namespace asio = boost::asio;
namespace sp = sparkplug;
namespace fc = function_code;
namespace metric_name = sparkplug_metric;
using modbus_map::RegisterEntry;

namespace {

// Commands waiting behind the one being carried out; past it a command is refused.
constexpr std::size_t kMaxQueuedCommands = 1024;
// Where the bdSeq of the latest CONNECT that may have reached the broker is kept, in state_dir.
constexpr std::string_view kBdSeqFile = "sparkplug-bdseq";

std::uint64_t epoch_ms() {
  return static_cast<std::uint64_t>(
      std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
          .count());
}

std::ifstream open_mqtt_file(const std::string& key, const std::string& path) {
  std::ifstream in(path);
  if (!in)
    throw std::runtime_error(key + ": cannot read " + path + " (check that it exists and the gateway may read it)");
  return in;
}

// A Modbus answer: registers or bits, or the exception code and why.
struct Answer {
  Bytes pdu;
  std::string refusal;  // the role gate's words when it refused it (it never reached the router)

  bool ok() const { return pdu.size() >= 2 && (pdu[0] & fc::kExceptionBit) == 0; }
  std::string error_text() const {
    if (pdu.size() < 2) return "no answer";
    char code[8];
    std::snprintf(code, sizeof code, "0x%02X", pdu[1]);
    const std::string text = "exception " + std::string(code) + " (" +
                             std::string(modbus_map::to_string(static_cast<modbus_map::ModbusException>(pdu[1]))) + ")";
    return refusal.empty() ? text : text + ": " + refusal;
  }
  std::vector<std::uint16_t> registers() const {
    std::vector<std::uint16_t> values;
    for (std::size_t i = 2; i + 1 < pdu.size(); i += 2)
      values.push_back(static_cast<std::uint16_t>(pdu[i] << 8 | pdu[i + 1]));
    return values;
  }
  bool bit(std::size_t index) const {
    const std::size_t byte = 2 + index / 8;
    return byte < pdu.size() && ((pdu[byte] >> (index % 8)) & 1) != 0;
  }
};

// A table field as a metric: its register value as the client sees it (two's complement for
// signed fields).
std::int64_t field_value(const RegisterEntry& entry, std::uint16_t reg) {
  return entry.min < 0 ? std::int64_t{static_cast<std::int16_t>(reg)} : std::int64_t{reg};
}

// The datatype a table field is born with: the register as a PLC reads it.
sp::DataType field_type(const RegisterEntry& entry) {
  return entry.min < 0 ? sp::DataType::Int16 : sp::DataType::UInt16;
}

sp::Metric field_metric(const std::string& name, const RegisterEntry& entry, std::optional<std::int64_t> value) {
  sp::Metric metric = sp::Metric::of(name, field_type(entry), std::monostate{});
  if (!value) {
    metric.value = std::monostate{};
  } else if (field_type(entry) == sp::DataType::Int16) {
    metric.value = *value;
  } else {
    metric.value = static_cast<std::uint64_t>(*value);
  }
  return metric;
}

// What a command metric carried, for refusals: `Boolean true`, `Float 2.5`, `String "fast"`.
std::string sent(const sp::Metric& metric) {
  const std::string type(sp::to_string(metric.type));
  return std::visit(
      [&](const auto& value) -> std::string {
        using T = std::decay_t<decltype(value)>;
        if constexpr (std::is_same_v<T, std::monostate>) {
          return type + " null";
        } else if constexpr (std::is_same_v<T, bool>) {
          return type + (value ? " true" : " false");
        } else if constexpr (std::is_same_v<T, std::string>) {
          return type + " \"" + value.substr(0, 40) + "\"";
        } else {
          return type + " " + fmt::format("{}", value);
        }
      },
      metric.value);
}

}  // namespace

Expected<std::int64_t> command_value(const sp::Metric& metric, sp::DataType born_as) {
  const std::string born = std::string(sp::to_string(born_as));
  if (born_as == sp::DataType::Boolean) {
    if (const auto* flag = std::get_if<bool>(&metric.value); flag && metric.type == sp::DataType::Boolean) {
      return std::int64_t{*flag ? 1 : 0};
    }
    return unexpected("got " + sent(metric) + ", the metric is Boolean (send true or false)");
  }
  const auto range = sp::integer_range(born_as);
  const auto value = sp::integer_value(metric.value);
  const bool integer =
      std::holds_alternative<std::int64_t>(metric.value) || std::holds_alternative<std::uint64_t>(metric.value);
  if (!range || !sp::integer_range(metric.type) || !integer || !value) {
    return unexpected("got " + sent(metric) + ", the metric is " + born + " (send a whole number, datatype " + born +
                      " as in the birth)");
  }
  if (*value < range->min || *value > range->max) {
    return unexpected(std::to_string(*value) + " does not fit " + born + " (" + std::to_string(range->min) + ".." +
                      std::to_string(range->max) + "), the metric's datatype in its birth");
  }
  return *value;
}

Expected<std::uint16_t> device_command_value(const sp::Metric& metric, const modbus_map::RegisterMap& map,
                                             const RegisterEntry& entry) {
  const auto value = command_value(metric, field_type(entry));
  if (!value) return unexpected(value.error());
  const auto checked = map.check_write(entry, *value);
  if (!checked) return unexpected(modbus_map::to_string(checked.error()));
  return checked->register_value;
}

std::string read_mqtt_files(const config::MqttConfig& mqtt) {
  if (mqtt.tls) {
    open_mqtt_file("mqtt.tls.ca", mqtt.tls->ca);
    if (!mqtt.tls->certificate.empty()) {
      open_mqtt_file("mqtt.tls.certificate", mqtt.tls->certificate);
      open_mqtt_file("mqtt.tls.private_key", mqtt.tls->private_key);
    }
  }
  if (mqtt.password_file.empty()) return {};
  auto in = open_mqtt_file("mqtt.password_file", mqtt.password_file);
  std::string line;
  std::getline(in, line);
  if (!line.empty() && line.back() == '\r') line.pop_back();
  if (line.empty()) {
    throw std::runtime_error("mqtt.password_file: " + mqtt.password_file + " is empty; the password is its first line");
  }
  return line;
}

class SparkplugNode::Impl final : public std::enable_shared_from_this<SparkplugNode::Impl> {
 public:
  Impl(const config::Config& config, asio::io_context& io, UnitRouter& router, const RolePolicy& policy)
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
    }
    if (const std::string dir = config::effective_state_dir(config); !dir.empty()) {
      bd_seq_path_ = (std::filesystem::path(dir) / kBdSeqFile).string();
    }
  }

  void start() {
    MqttLinkOptions options;
    options.broker = settings_.broker;
    options.client_id = settings_.client_id;
    options.username = settings_.username;
    options.password = read_mqtt_files(settings_);
    options.tls = settings_.tls;
    options.keepalive = settings_.keepalive;
    options.reconnect_min = settings_.reconnect_min;
    options.reconnect_max = settings_.reconnect_max;
    options.subscriptions = {topic(sp::MessageType::NCmd), topic(sp::MessageType::DCmd, "+")};
    if (!settings_.primary_host_id.empty()) options.subscriptions.push_back(sp::state_topic(settings_.primary_host_id));
    load_bd_seq();
    std::weak_ptr<Impl> weak = shared_from_this();
    replies_ = std::make_shared<Replies>(weak);
    MqttLink::Events events;
    events.will = [this] { return next_will(); };
    events.connect_sent = [this] {
      bd_seq_ = candidate_bd_seq_;
      candidate_used_ = true;
    };
    events.connected = [this, weak] {
      asio::post(io_, [weak] {
        if (auto self = weak.lock()) self->on_connected();
      });
    };
    events.disconnected = [this, weak](const std::string&) {
      asio::post(io_, [weak] {
        if (auto self = weak.lock()) self->on_disconnected();
      });
    };
    events.message = [this, weak](std::string topic, Bytes payload) {
      asio::post(io_, [weak, topic = std::move(topic), payload = std::move(payload)]() mutable {
        if (auto self = weak.lock()) self->on_message(topic, payload);
      });
    };
    link_ = std::make_unique<MqttLink>(std::move(options), std::move(events));
    link_->start();
    spdlog::info("mqtt: Sparkplug B edge node {}/{} with {} device(s), broker {}{}", settings_.group_id,
                 settings_.edge_node_id, devices_.size(), settings_.broker.to_string(),
                 settings_.primary_host_id.empty() ? std::string() : ", primary host " + settings_.primary_host_id);
    asio::post(io_, [weak] {
      if (auto self = weak.lock()) self->schedule();
    });
  }

  void stop() {
    if (!link_ || stopping_.exchange(true)) return;
    // The node's own NDEATH (a clean DISCONNECT makes the broker drop the will).
    link_->stop(death(bd_seq_.load()));
  }

  SparkplugStats stats() const {
    std::lock_guard lock(stats_mutex_);
    SparkplugStats copy = stats_;
    if (link_) copy.link = link_->stats();
    copy.devices = devices_.size();
    return copy;
  }

  // The router's answer to request `serial` (io thread), through Replies.
  void deliver(std::uint64_t serial, Bytes response_pdu) {
    const auto it = pending_.find(serial);
    if (it == pending_.end()) return;
    auto done = std::move(it->second);
    pending_.erase(it);
    done(Answer{std::move(response_pdu), {}});
  }

 private:
  // Where the router's answers go. A Reply keeps its target alive for as long as the work runs
  // (a bus completion may come after the node is gone): that target is this small forwarder, not
  // the node, so the node (and its timer) never outlives the io_context it was made on.
  class Replies final : public Reply::Target {
   public:
    explicit Replies(std::weak_ptr<Impl> node) : node_(std::move(node)) {}
    void deliver(std::uint64_t serial, Bytes response_pdu) override {
      if (auto node = node_.lock()) node->deliver(serial, std::move(response_pdu));
    }

   private:
    std::weak_ptr<Impl> node_;
  };

  struct MetricSlot {
    std::string name;
    const RegisterEntry* entry = nullptr;
    bool from_cache = false;  // FC04 (poll cache); else FC03 (live), read at birth and after writes
    std::uint32_t deadband = 0;
    std::optional<std::int64_t> value;  // as last published
  };
  struct Device {
    std::uint8_t unit_id = 0;
    std::string id;
    const ServoUnit* unit = nullptr;
    std::vector<MetricSlot> metrics;
    std::optional<ReadRegistersRequest> cache_read;  // one FC04 over every cached metric
    std::vector<ReadRegistersRequest> live_reads;    // FC03 runs over the others
    bool born = false;
    bool busy = false;  // a read of this device is under way
    std::uint16_t status = 0;
    std::string last_command;
    std::chrono::steady_clock::time_point reported;
  };
  struct Command {
    std::optional<std::size_t> device;  // nullopt: a node command
    sp::Metric metric;
  };

  Device make_device(const config::ServoConfig& servo, const ServoUnit& unit) {
    Device device;
    device.unit_id = servo.unit_id;
    device.id = config::sparkplug_device_id(servo);
    device.unit = &unit;
    const auto& map = unit.map;
    std::vector<const RegisterEntry*> cached, live;
    for (const auto& entry : map.entries()) {
      if (!entry.readable && !entry.writable) continue;
      MetricSlot slot;
      slot.name = std::string(entry.shown->name);
      slot.entry = &entry;
      slot.from_cache = entry.readable && map.plan_input_read(entry.address, 1, unit.poll_block).has_value();
      for (const auto& band : settings_.deadbands) {
        if (band.field == slot.name) slot.deadband = band.deadband;
      }
      if (slot.from_cache) cached.push_back(&entry);
      if (entry.readable && !slot.from_cache) live.push_back(&entry);
      device.metrics.push_back(std::move(slot));
    }
    if (!cached.empty()) {
      const auto first = cached.front()->address;
      const auto count = static_cast<std::uint16_t>(cached.back()->address - first + 1);
      if (count <= limits::kReadRegisters && map.plan_input_read(first, count, unit.poll_block)) {
        device.cache_read = ReadRegistersRequest{fc::kReadInputRegisters, first, count};
      } else {
        for (auto& slot : device.metrics) {  // cannot be read in one: read them live instead
          if (slot.from_cache) live.push_back(slot.entry);
          slot.from_cache = false;
        }
        std::sort(live.begin(), live.end(), [](auto* a, auto* b) { return a->address < b->address; });
      }
    }
    // Runs of live fields, each one FC03 the map accepts (at most 125 registers).
    for (std::size_t i = 0; i < live.size();) {
      std::size_t j = i + 1;
      while (j < live.size() && live[j]->address - live[i]->address < limits::kReadRegisters &&
             map.plan_holding_read(live[i]->address,
                                   static_cast<std::uint16_t>(live[j]->address - live[i]->address + 1))) {
        ++j;
      }
      device.live_reads.push_back(
          ReadRegistersRequest{fc::kReadHoldingRegisters, live[i]->address,
                               static_cast<std::uint16_t>(live[j - 1]->address - live[i]->address + 1)});
      i = j;
    }
    return device;
  }

  std::string topic(sp::MessageType type, const std::string& device = "") const {
    return sp::topic_text(sp::Topic{settings_.group_id, type, settings_.edge_node_id, device});
  }

  // ---- bdSeq (spec: +1 per CONNECT, 0..255, the NDEATH in the will names its NBIRTH) ----
  //
  // The candidate is the bdSeq of the next CONNECT; it is used up once a CONNECT went out
  // (MqttLink's connect_sent), so attempts that never reached the broker cost none. With a
  // state_dir it is written to the file *before* the attempt: a crash can then skip a value but
  // never send one twice, which a host would take for the old session.

  void load_bd_seq() {
    if (bd_seq_path_.empty()) {
      spdlog::info(
          "mqtt: no state_dir: the Sparkplug bdSeq starts at 0 at every start (config/README.md "
          "\"state_dir\")");
      return;
    }
    {
      const auto read = read_state_file(bd_seq_path_);
      if (!read) {
        spdlog::warn("mqtt: {}; the bdSeq starts at 0", read.error());
        return;
      }
      const auto& text = *read;
      if (!text) return;  // first start
      std::uint64_t last = 0;
      const char* end = text->data() + text->size();
      const auto [rest, error] = std::from_chars(text->data(), end, last);
      if (error != std::errc() || last > 255 || (rest != end && *rest != '\n')) {
        spdlog::warn("mqtt: {} does not hold a bdSeq (0..255); starting at 0", bd_seq_path_);
        return;
      }
      candidate_bd_seq_ = last;
      stored_bd_seq_ = last;
      candidate_used_ = true;
    }
  }

  // On the link thread before every connection attempt: the NDEATH the broker sends for us if the
  // connection dies, with the bdSeq the coming NBIRTH will carry.
  MqttWill next_will() {
    if (candidate_used_) {
      candidate_bd_seq_ = (candidate_bd_seq_ + 1) % 256;
      candidate_used_ = false;
    }
    if (!bd_seq_path_.empty() && stored_bd_seq_ != candidate_bd_seq_) {
      if (const auto written = write_file_atomically(bd_seq_path_, std::to_string(candidate_bd_seq_) + "\n")) {
        stored_bd_seq_ = candidate_bd_seq_;
        bd_seq_store_failing_ = false;
      } else if (!bd_seq_store_failing_) {
        bd_seq_store_failing_ = true;
        spdlog::warn("mqtt: the bdSeq is not kept across restarts: {} (check state_dir)", written.error());
      }
    }
    return death(candidate_bd_seq_);
  }

  MqttWill death(std::uint64_t bd_seq) const {
    sp::Payload payload;
    payload.timestamp = epoch_ms();
    payload.metrics.push_back(sp::Metric::int64(std::string(sp::kBdSeqMetric), static_cast<std::int64_t>(bd_seq)));
    return MqttWill{topic(sp::MessageType::NDeath), sp::encode(payload), 1, false};
  }

  // Stamps the payload (and, on births and data, every metric without its own time: Sparkplug
  // 3.0 wants one on each) and the next seq.
  void publish(sp::MessageType type, sp::Payload payload, const std::string& device = "") {
    const std::uint64_t now = epoch_ms();
    payload.timestamp = now;
    if (type != sp::MessageType::NDeath && type != sp::MessageType::DDeath) {
      for (auto& metric : payload.metrics) {
        if (!metric.timestamp) metric.timestamp = now;
      }
    }
    payload.seq = seq_;
    seq_ = (seq_ + 1) % 256;
    if (link_->publish(topic(type, device), sp::encode(payload), 0)) {
      std::lock_guard lock(stats_mutex_);
      ++stats_.published[static_cast<std::size_t>(type)];
    }
  }

  // ---- requests to the router, as a Modbus client ----

  // Commands pass the role gate first; the node's own reads (what it publishes) do not: the
  // role says what the hosts may change, not what the node reports.
  void ask(std::uint8_t unit_id, const Request& request, std::function<void(const Answer&)> done) {
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
  void read_all(std::uint8_t unit_id, std::vector<ReadRegistersRequest> reads, std::vector<Answer> answers,
                std::function<void(std::vector<Answer>)> done) {
    if (answers.size() == reads.size() || (!answers.empty() && !answers.back().ok())) return done(std::move(answers));
    const ReadRegistersRequest next = reads[answers.size()];
    ask(unit_id, next,
        [this, unit_id, reads = std::move(reads), answers = std::move(answers),
         done = std::move(done)](const Answer& answer) mutable {
          answers.push_back(answer);
          read_all(unit_id, std::move(reads), std::move(answers), std::move(done));
        });
  }

  // ---- the session ----

  void on_connected() {
    if (stopping_) return;
    connected_ = true;
    session_ = false;
    for (auto& device : devices_) device.born = false;
    if (settings_.primary_host_id.empty()) return node_birth();
    // The host's retained STATE arrives right after the subscription (config/README.md
    // "primary_host_id").
    spdlog::info("mqtt: connected; waiting for primary host {} to be online ({}) before NBIRTH",
                 settings_.primary_host_id, sp::state_topic(settings_.primary_host_id));
  }

  void on_disconnected() {
    connected_ = false;
    session_ = false;
    for (auto& device : devices_) device.born = false;
    set_online_count();
  }

  // NBIRTH (seq 0), then every device's DBIRTH from the next ticks.
  void node_birth() {
    session_ = true;
    seq_ = 0;
    for (auto& device : devices_) device.born = false;
    set_online_count();
    publish_node_birth();
  }

  // The primary host's STATE (Sparkplug 3.0): births wait for online; offline ends a born
  // session (NDEATH, DISCONNECT, connect again, wait). Older timestamps are stale: ignored.
  void on_host_state(const Bytes& bytes) {
    const std::string& host = settings_.primary_host_id;
    const auto state =
        sp::parse_host_state(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
    if (!state) return bad_message("mqtt: ignored the STATE of primary host " + host + ": " + state.error());
    if (host_timestamp_ && state->timestamp < *host_timestamp_) {
      spdlog::info("mqtt: ignored a stale STATE of primary host {} (timestamp {} is before {})", host, state->timestamp,
                   *host_timestamp_);
      return;
    }
    host_timestamp_ = state->timestamp;
    if (state->online) {
      if (connected_ && !session_ && !stopping_) {
        spdlog::info("mqtt: primary host {} is online: NBIRTH", host);
        node_birth();
      }
      return;
    }
    if (!session_) {
      if (connected_) spdlog::info("mqtt: primary host {} is offline; waiting for it before NBIRTH", host);
      return;
    }
    spdlog::warn("mqtt: primary host {} went offline: NDEATH, reconnecting, and no births until it is back", host);
    on_disconnected();
    link_->reconnect(death(bd_seq_.load()));
  }

  void publish_node_birth() {
    sp::Payload payload;
    payload.metrics.push_back(
        sp::Metric::int64(std::string(sp::kBdSeqMetric), static_cast<std::int64_t>(bd_seq_.load())));
    payload.metrics.push_back(sp::Metric::boolean(std::string(sp::kRebirthMetric), false));
    payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kVersion), SMS_GATEWAY_VERSION));
    payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kEStop), estop_));
    payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kWatchdogTripped), tripped_));
    payload.metrics.push_back(sp::Metric::uint16(std::string(metric_name::kStopsOwed), stops_owed_));
    for (const auto& name : heartbeats_) {
      auto metric = sp::Metric::uint16(name, 0);
      metric.value = std::monostate{};  // write-only: the value is whatever the host sends next
      payload.metrics.push_back(std::move(metric));
    }
    publish(sp::MessageType::NBirth, std::move(payload));
  }

  void schedule() {
    if (stopping_) return;
    timer_.expires_after(settings_.data_period);
    timer_.async_wait([weak = weak_from_this()](const boost::system::error_code& error) {
      if (auto self = weak.lock(); self && !error) self->tick();
    });
  }

  void tick() {
    schedule();
    if (!session_ || stopping_) return;
    read_node_state();
    const auto now = std::chrono::steady_clock::now();
    for (std::size_t i = 0; i < devices_.size(); ++i) {
      if (!devices_[i].busy) check_device(i, now);
    }
  }

  void read_node_state() {
    ask(config_.modbus_tcp.gateway_unit_id, ReadBitsRequest{fc::kReadCoils, gateway_unit_layout::kEStopCoil, 2},
        [this](const Answer& answer) {
          if (!answer.ok() || !session_) return;
          const bool estop = answer.bit(0), tripped = answer.bit(1);
          if (estop == estop_ && tripped == tripped_) return;
          sp::Payload payload;
          if (estop != estop_) payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kEStop), estop));
          if (tripped != tripped_) {
            payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kWatchdogTripped), tripped));
          }
          estop_ = estop;
          tripped_ = tripped;
          publish(sp::MessageType::NData, std::move(payload));
        });
    // A stop that could not be delivered yet (docs/SAFETY.md): a host must see it, not only a PLC.
    ask(config_.modbus_tcp.gateway_unit_id,
        ReadRegistersRequest{fc::kReadInputRegisters, gateway_unit_layout::kOwedStops, 1},
        [this](const Answer& answer) {
          if (!answer.ok() || !session_) return;
          const auto registers = answer.registers();
          if (registers.empty() || registers[0] == stops_owed_) return;
          stops_owed_ = registers[0];
          sp::Payload payload;
          payload.metrics.push_back(sp::Metric::uint16(std::string(metric_name::kStopsOwed), stops_owed_));
          publish(sp::MessageType::NData, std::move(payload));
        });
  }

  // Facts first (online, status, counters: FC04 1000-1007), then birth, death or data.
  void check_device(std::size_t index, std::chrono::steady_clock::time_point now) {
    Device& device = devices_[index];
    device.busy = true;
    ask(device.unit_id,
        ReadRegistersRequest{fc::kReadInputRegisters, servo_facts_layout::kFirstRegister,
                             servo_facts_layout::kRegisterCount},
        [this, index, now](const Answer& answer) {
          Device& device = devices_[index];
          const auto facts = answer.registers();
          if (!answer.ok() || facts.size() < servo_facts_layout::kRegisterCount || !session_) {
            device.busy = false;
            return;
          }
          const bool online = facts[servo_facts_layout::kOnline] != 0;
          if (!online) {
            if (device.born) publish_device_death(device);
            device.busy = false;
            return;
          }
          if (!device.born) return birth(index, facts);
          data(index, facts, now);
        });
  }

  void birth(std::size_t index, const std::vector<std::uint16_t>& facts) {
    Device& device = devices_[index];
    std::vector<ReadRegistersRequest> reads = device.live_reads;
    if (device.cache_read) reads.insert(reads.begin(), *device.cache_read);
    read_all(device.unit_id, reads, {}, [this, index, reads, facts](std::vector<Answer> answers) {
      Device& device = devices_[index];
      device.busy = false;
      if (answers.size() != reads.size() || !answers.back().ok() || !session_) return;  // next tick again
      for (std::size_t i = 0; i < reads.size(); ++i) store(device, reads[i], answers[i].registers());
      const std::uint64_t acquired = acquisition_time(facts[servo_facts_layout::kCacheAge]);
      sp::Payload payload;
      for (const auto& slot : device.metrics) {
        auto metric = field_metric(slot.name, *slot.entry, slot.value);
        metric.eng_unit = std::string(slot.entry->shown->unit);
        metric.read_only = !slot.entry->writable;
        if (slot.from_cache) metric.timestamp = acquired;
        payload.metrics.push_back(std::move(metric));
      }
      device.status = facts[servo_facts_layout::kStatus];
      append_facts(payload, device, facts, true);
      device.born = true;
      device.reported = std::chrono::steady_clock::now();
      publish(sp::MessageType::DBirth, std::move(payload), device.id);
      set_online_count();
    });
  }

  void data(std::size_t index, std::vector<std::uint16_t> facts, std::chrono::steady_clock::time_point now) {
    Device& device = devices_[index];
    const bool report_all = settings_.report_period.count() > 0 && now - device.reported >= settings_.report_period;
    if (!device.cache_read) {
      device.busy = false;
      if (report_all || facts[servo_facts_layout::kStatus] != device.status)
        publish_data(device, facts, {}, report_all);
      return;
    }
    ask(device.unit_id, *device.cache_read, [this, index, facts, report_all](const Answer& answer) {
      Device& device = devices_[index];
      device.busy = false;
      if (!answer.ok() || !session_ || !device.born) return;
      const auto registers = answer.registers();
      std::vector<std::size_t> changed;
      for (std::size_t m = 0; m < device.metrics.size(); ++m) {
        auto& slot = device.metrics[m];
        if (!slot.from_cache) continue;
        const std::size_t offset = slot.entry->address - device.cache_read->address;
        if (offset >= registers.size()) continue;
        const std::int64_t value = field_value(*slot.entry, registers[offset]);
        const bool moved = !slot.value || (value != *slot.value && std::llabs(value - *slot.value) >= slot.deadband);
        if (moved || report_all) {
          slot.value = value;
          changed.push_back(m);
        }
      }
      if (!changed.empty() || facts[servo_facts_layout::kStatus] != device.status || report_all)
        publish_data(device, facts, changed, report_all);
    });
  }

  void publish_data(Device& device, const std::vector<std::uint16_t>& facts, const std::vector<std::size_t>& changed,
                    bool report_all) {
    sp::Payload payload;
    const std::uint64_t acquired = acquisition_time(facts[servo_facts_layout::kCacheAge]);
    for (const auto m : changed) {
      auto metric = field_metric(device.metrics[m].name, *device.metrics[m].entry, device.metrics[m].value);
      metric.timestamp = acquired;
      payload.metrics.push_back(std::move(metric));
    }
    if (report_all) {
      for (const auto& slot : device.metrics) {
        if (!slot.from_cache) payload.metrics.push_back(field_metric(slot.name, *slot.entry, slot.value));
      }
      device.reported = std::chrono::steady_clock::now();
    }
    append_facts(payload, device, facts, report_all);
    publish(sp::MessageType::DData, std::move(payload), device.id);
  }

  // Status on change (and in births and full reports); the counters only in births and reports,
  // since they change on every poll.
  void append_facts(sp::Payload& payload, Device& device, const std::vector<std::uint16_t>& facts, bool everything) {
    if (everything || facts[servo_facts_layout::kStatus] != device.status) {
      payload.metrics.push_back(
          sp::Metric::uint16(std::string(metric_name::kStatus), facts[servo_facts_layout::kStatus]));
      device.status = facts[servo_facts_layout::kStatus];
    }
    if (everything) {
      // UInt64 (long_value) rather than UInt32: the spec puts UInt32 in int_value, Tahu's Java and
      // JS decoders read it from long_value; for UInt64 both agree (docs/DECISIONS.md).
      namespace at = servo_facts_layout;
      const auto counter = [&](std::size_t offset) { return std::uint64_t{facts[offset]} << 16 | facts[offset + 1]; };
      payload.metrics.push_back(sp::Metric::uint64(std::string(metric_name::kRepliesOk), counter(at::kRepliesOk)));
      payload.metrics.push_back(sp::Metric::uint64(std::string(metric_name::kTimeouts), counter(at::kTimeouts)));
      payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kLastCommand), device.last_command));
    }
  }

  // The poll's time from the cache age (facts register 1002, ms, 65535: unknown or older).
  static std::uint64_t acquisition_time(std::uint16_t age_ms) {
    const std::uint64_t now = epoch_ms();
    return age_ms == 0xFFFF ? now : now - age_ms;
  }

  void store(Device& device, const ReadRegistersRequest& read, const std::vector<std::uint16_t>& registers) {
    for (auto& slot : device.metrics) {
      if (!slot.entry->readable || slot.entry->address < read.address) continue;
      const std::size_t offset = slot.entry->address - read.address;
      if (offset < registers.size() && offset < read.count) slot.value = field_value(*slot.entry, registers[offset]);
    }
  }

  void publish_device_death(Device& device) {
    device.born = false;
    publish(sp::MessageType::DDeath, sp::Payload{}, device.id);
    spdlog::info("mqtt: device {} (unit {}) is offline: DDEATH", device.id, device.unit_id);
    set_online_count();
  }

  void set_online_count() {
    std::size_t online = 0;
    for (const auto& device : devices_) online += device.born ? 1 : 0;
    std::lock_guard lock(stats_mutex_);
    stats_.devices_online = online;
  }

  // ---- commands ----

  void on_message(const std::string& topic_text, const Bytes& bytes) {
    if (!settings_.primary_host_id.empty() && topic_text == sp::state_topic(settings_.primary_host_id)) {
      return on_host_state(bytes);
    }
    const auto topic = sp::parse_topic(topic_text);
    if (!topic || topic->group != settings_.group_id || topic->edge_node != settings_.edge_node_id ||
        (topic->type != sp::MessageType::NCmd && topic->type != sp::MessageType::DCmd)) {
      return bad_message("mqtt: ignored a message on " + topic_text + " (not this node's NCMD/DCMD)");
    }
    std::optional<std::size_t> device;
    if (topic->type == sp::MessageType::DCmd) {
      for (std::size_t i = 0; i < devices_.size(); ++i) {
        if (devices_[i].id == topic->device) device = i;
      }
      if (!device) {
        return bad_message("mqtt: refused the DCMD on " + topic_text + ": no device `" + topic->device +
                           "` on this node (devices are the servo names, else unit-<N>)");
      }
    }
    // Metrics without a datatype (as commands should be sent) are read as their birth said.
    const auto payload = sp::decode(bytes, [&](std::string_view name) { return birth_type(device, name); });
    if (!payload) return bad_message("mqtt: refused the command on " + topic_text + ": " + payload.error());
    if (payload->metrics.empty()) {
      return bad_message("mqtt: ignored the " + std::string(sp::to_string(topic->type)) + " on " + topic_text +
                         ": it carries no metric (" + std::to_string(bytes.size()) + " bytes)");
    }
    for (const auto& metric : payload->metrics) {
      if (commands_.size() >= kMaxQueuedCommands) {
        refuse_command(device, metric.name,
                       "the command queue is full (" + std::to_string(kMaxQueuedCommands) +
                           " waiting); the bus is not keeping up");
        continue;
      }
      commands_.push_back(Command{device, metric});
    }
    if (!command_running_) run_next_command();
  }

  // The datatype `name` has in this node's NBIRTH (no device) or the device's DBIRTH.
  sp::DataType birth_type(std::optional<std::size_t> device, std::string_view name) const {
    if (device) {
      for (const auto& slot : devices_[*device].metrics) {
        if (slot.name == name) return field_type(*slot.entry);
      }
      if (name == metric_name::kStatus) return sp::DataType::UInt16;
      if (name == metric_name::kRepliesOk || name == metric_name::kTimeouts) return sp::DataType::UInt64;
      if (name == metric_name::kLastCommand) return sp::DataType::String;
      return sp::DataType::Unknown;
    }
    if (name == sp::kBdSeqMetric) return sp::DataType::Int64;
    if (name == sp::kRebirthMetric || name == metric_name::kEStop || name == metric_name::kWatchdogTripped) {
      return sp::DataType::Boolean;
    }
    if (name == metric_name::kVersion) return sp::DataType::String;
    for (const auto& heartbeat : heartbeats_) {
      if (heartbeat == name) return sp::DataType::UInt16;
    }
    return sp::DataType::Unknown;
  }

  void bad_message(const std::string& text) {
    spdlog::warn("{}", text);
    std::lock_guard lock(stats_mutex_);
    ++stats_.bad_messages;
  }

  void run_next_command() {
    if (commands_.empty()) {
      command_running_ = false;
      return;
    }
    command_running_ = true;
    Command command = std::move(commands_.front());
    commands_.pop_front();
    if (command.device) return run_device_command(*command.device, command.metric);
    run_node_command(command.metric);
  }

  void run_device_command(std::size_t index, const sp::Metric& metric) {
    Device& device = devices_[index];
    const auto slot = std::find_if(device.metrics.begin(), device.metrics.end(),
                                   [&](const MetricSlot& s) { return s.name == metric.name; });
    if (slot == device.metrics.end()) return finish_command(index, metric.name, "no such metric on this device");
    const RegisterEntry& entry = *slot->entry;
    const auto reg = device_command_value(metric, device.unit->map, entry);
    if (!reg) return finish_command(index, metric.name, reg.error() + "; nothing written");
    const std::int64_t written = field_value(entry, *reg);
    const std::string what = metric.name + " := " + std::to_string(written);
    const std::size_t slot_index = static_cast<std::size_t>(slot - device.metrics.begin());
    ask(device.unit_id, WriteRegistersRequest{fc::kWriteSingleRegister, entry.address, {*reg}},
        [this, index, slot_index, what, written](const Answer& answer) {
          auto& slot = devices_[index].metrics[slot_index];
          if (!answer.ok()) return finish_command(index, slot.name, what + ": " + answer.error_text());
          if (!slot.entry->readable) return finish_command(index, slot.name, "", what);
          read_back(index, slot_index, written, what);
        });
  }

  // After a write, the field as the servo now holds it (FC03, live): a servo may clamp or refuse
  // a value silently (a goal below its angle limit holds the limit), and the host must see that,
  // not the value it sent.
  void read_back(std::size_t index, std::size_t slot_index, std::int64_t written, const std::string& what) {
    const RegisterEntry& entry = *devices_[index].metrics[slot_index].entry;
    ask(devices_[index].unit_id, ReadRegistersRequest{fc::kReadHoldingRegisters, entry.address, 1},
        [this, index, slot_index, written, what](const Answer& answer) {
          Device& device = devices_[index];
          auto& slot = device.metrics[slot_index];
          const auto registers = answer.registers();
          if (!answer.ok() || registers.empty()) {
            return finish_command(index, slot.name, "", what + " (read-back failed: " + answer.error_text() + ")");
          }
          const std::int64_t held = field_value(*slot.entry, registers[0]);
          slot.value = held;
          finish_command(index, slot.name, "", held != written ? what + ", reads back " + std::to_string(held) : what,
                         device.born);
        });
  }

  // Ends a device command: logs a refusal, records "ok: ..." or "refused: ..." as the device's
  // Gateway/Last Command and publishes it (with the value read back after a write).
  void finish_command(std::size_t index, const std::string& name, const std::string& refusal,
                      const std::string& done = "", bool report_value = false) {
    Device& device = devices_[index];
    {
      std::lock_guard lock(stats_mutex_);
      ++(refusal.empty() ? stats_.commands_ok : stats_.commands_refused);
    }
    if (refusal.empty()) {
      device.last_command = "ok: " + done;
    } else {
      device.last_command = "refused: " + name + ": " + refusal;
      spdlog::warn("mqtt: DCMD for {} (unit {}) refused: {}: {}", device.id, device.unit_id, name, refusal);
    }
    if (session_ && device.born) {
      sp::Payload payload;
      if (report_value) {
        const auto& slot = *std::find_if(device.metrics.begin(), device.metrics.end(),
                                         [&](const MetricSlot& s) { return s.name == name; });
        payload.metrics.push_back(field_metric(slot.name, *slot.entry, slot.value));
      }
      payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kLastCommand), device.last_command));
      publish(sp::MessageType::DData, std::move(payload), device.id);
    }
    run_next_command();
  }

  void run_node_command(const sp::Metric& metric) {
    const auto done = [this, name = metric.name](const Answer& answer) {
      finish_node_command(name, answer.ok() ? "" : answer.error_text());
    };
    const std::uint8_t gateway = config_.modbus_tcp.gateway_unit_id;
    const sp::DataType born_as = birth_type(std::nullopt, metric.name);
    // The Boolean controls and the UInt16 heartbeats; bdSeq and the version are the node's own.
    const bool writable = born_as == sp::DataType::Boolean || born_as == sp::DataType::UInt16;
    if (born_as == sp::DataType::Unknown || !writable) {
      return finish_node_command(metric.name, born_as == sp::DataType::Unknown ? "no such node metric" : "read-only");
    }
    const auto value = command_value(metric, born_as);  // Boolean 0/1, UInt16 0..65535: the registers' range
    if (!value) return finish_node_command(metric.name, value.error() + "; nothing written");
    if (metric.name == sp::kRebirthMetric) {
      if (*value != 0 && session_) node_birth();  // NBIRTH again, then every DBIRTH
      return finish_node_command(metric.name, "");
    }
    if (metric.name == metric_name::kEStop) {
      return ask(gateway, WriteBitsRequest{fc::kWriteSingleCoil, gateway_unit_layout::kEStopCoil, {*value != 0}}, done);
    }
    if (metric.name == metric_name::kWatchdogTripped) {
      if (*value != 0) return finish_node_command(metric.name, "only false (re-arm) can be written");
      return ask(gateway, WriteBitsRequest{fc::kWriteSingleCoil, gateway_unit_layout::kWatchdogCoil, {false}}, done);
    }
    for (std::size_t bus = 0; bus < heartbeats_.size(); ++bus) {
      if (metric.name != heartbeats_[bus]) continue;
      return ask(gateway,
                 WriteRegistersRequest{fc::kWriteSingleRegister,
                                       static_cast<std::uint16_t>(config::kHeartbeatRegisterBase + bus),
                                       {static_cast<std::uint16_t>(*value)}},
                 done);
    }
    finish_node_command(metric.name, "no such node metric");
  }

  void finish_node_command(const std::string& name, const std::string& refusal) {
    {
      std::lock_guard lock(stats_mutex_);
      ++(refusal.empty() ? stats_.commands_ok : stats_.commands_refused);
    }
    if (!refusal.empty()) spdlog::warn("mqtt: NCMD refused: {}: {}", name, refusal);
    run_next_command();
  }

  void refuse_command(std::optional<std::size_t> device, const std::string& name, const std::string& why) {
    std::lock_guard lock(stats_mutex_);
    ++stats_.commands_refused;
    spdlog::warn("mqtt: {} refused: {}: {}", device ? "DCMD for " + devices_[*device].id : std::string("NCMD"), name,
                 why);
  }

  const config::Config& config_;
  const config::MqttConfig& settings_;
  asio::io_context& io_;
  UnitRouter& router_;
  AccessGate gate_;  // the hosts' commands, as mqtt.role; counted among the refused commands
  asio::steady_timer timer_;
  std::unique_ptr<MqttLink> link_;
  std::shared_ptr<Replies> replies_;
  std::vector<Device> devices_;
  std::vector<std::string> heartbeats_;
  std::unordered_map<std::uint64_t, std::function<void(const Answer&)>> pending_;
  std::uint64_t next_serial_ = 1;
  std::deque<Command> commands_;
  bool command_running_ = false;
  bool connected_ = false;                       // an MQTT session is up
  bool session_ = false;                         // connected and NBIRTH sent
  std::optional<std::uint64_t> host_timestamp_;  // of the primary host's latest STATE
  bool estop_ = false;
  bool tripped_ = false;
  std::uint16_t stops_owed_ = 0;
  std::uint64_t seq_ = 0;
  std::atomic<std::uint64_t> bd_seq_{0};  // of this session's CONNECT (its NBIRTH's)
  // Link thread only: the bdSeq of the next CONNECT, whether a CONNECT used it, the file.
  std::uint64_t candidate_bd_seq_ = 0;
  bool candidate_used_ = false;
  std::string bd_seq_path_;  // empty: kept in memory only
  std::optional<std::uint64_t> stored_bd_seq_;
  bool bd_seq_store_failing_ = false;
  std::atomic<bool> stopping_{false};
  mutable std::mutex stats_mutex_;
  SparkplugStats stats_;
};

SparkplugNode::SparkplugNode(const config::Config& config, asio::io_context& io, UnitRouter& router,
                             const RolePolicy& policy)
    : impl_(std::make_shared<Impl>(config, io, router, policy)) {}
SparkplugNode::~SparkplugNode() { impl_->stop(); }
void SparkplugNode::start() { impl_->start(); }
void SparkplugNode::stop() { impl_->stop(); }
SparkplugStats SparkplugNode::stats() const { return impl_->stats(); }

}  // namespace sms::gateway
