// The Sparkplug node's MQTT session: the link, the CONNECT's bdSeq and its will (the NDEATH),
// the primary host's STATE, publishing with seq.
#include "gateway/mqtt/sparkplug_node_impl.h"

#include <charconv>
#include <filesystem>
#include <fstream>
#include <stdexcept>

#include <spdlog/spdlog.h>
#include <boost/asio/post.hpp>

#include "gateway/units/state_file.h"

namespace sms::gateway {

namespace {

std::ifstream open_mqtt_file(const std::string& key, const std::string& path) {
  std::ifstream in(path);
  if (!in)
    throw std::runtime_error(key + ": cannot read " + path + " (check that it exists and the gateway may read it)");
  return in;
}

}  // namespace

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
void SparkplugNode::Impl::start() {
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

void SparkplugNode::Impl::stop() {
  if (!link_ || stopping_.exchange(true)) return;
  // The node's own NDEATH (a clean DISCONNECT makes the broker drop the will).
  link_->stop(death(bd_seq_.load()));
}

std::string SparkplugNode::Impl::topic(sp::MessageType type, const std::string& device) const {
  return sp::topic_text(sp::Topic{settings_.group_id, type, settings_.edge_node_id, device});
}

// bdSeq (spec: +1 per CONNECT, 0..255, the NDEATH in the will names its NBIRTH).
//
// The candidate is the bdSeq of the next CONNECT; it is used up once a CONNECT went out
// (MqttLink's connect_sent), so attempts that never reached the broker cost none. With a
// state_dir it is written to the file *before* the attempt: a crash can then skip a value but
// never send one twice, which a host would take for the old session.

void SparkplugNode::Impl::load_bd_seq() {
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
MqttWill SparkplugNode::Impl::next_will() {
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

MqttWill SparkplugNode::Impl::death(std::uint64_t bd_seq) const {
  sp::Payload payload;
  payload.timestamp = epoch_ms();
  payload.metrics.push_back(sp::Metric::int64(std::string(sp::kBdSeqMetric), static_cast<std::int64_t>(bd_seq)));
  return MqttWill{topic(sp::MessageType::NDeath), sp::encode(payload), 1, false};
}

// Stamps the payload (and, on births and data, every metric without its own time: Sparkplug
// 3.0 wants one on each) and the next seq.
void SparkplugNode::Impl::publish(sp::MessageType type, sp::Payload payload, const std::string& device) {
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

void SparkplugNode::Impl::on_connected() {
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

void SparkplugNode::Impl::on_disconnected() {
  connected_ = false;
  session_ = false;
  for (auto& device : devices_) device.born = false;
  set_online_count();
}

// NBIRTH (seq 0), then every device's DBIRTH from the next ticks.
void SparkplugNode::Impl::node_birth() {
  session_ = true;
  seq_ = 0;
  for (auto& device : devices_) device.born = false;
  set_online_count();
  publish_node_birth();
}

// The primary host's STATE (Sparkplug 3.0): births wait for online; offline ends a born
// session (NDEATH, DISCONNECT, connect again, wait). Older timestamps are stale: ignored.
void SparkplugNode::Impl::on_host_state(const Bytes& bytes) {
  const std::string& host = settings_.primary_host_id;
  const auto state = sp::parse_host_state(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
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

}  // namespace sms::gateway
