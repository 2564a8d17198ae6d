#include "gateway/mqtt/mqtt_link.h"

#include <mosquitto.h>
#include <openssl/ssl.h>
#include <sys/socket.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <mutex>
#include <stdexcept>

#include <spdlog/spdlog.h>

namespace sms::gateway {
namespace {

std::once_flag library_once;

std::string error_text(int rc) {
  if (rc == MOSQ_ERR_ERRNO) return std::strerror(errno);
  return mosquitto_strerror(rc);
}

}  // namespace

MqttLink::MqttLink(MqttLinkOptions options, Events events) : options_(std::move(options)), events_(std::move(events)) {}

MqttLink::~MqttLink() { stop(); }

void MqttLink::start() {
  std::call_once(library_once, [] { mosquitto_lib_init(); });
  client_ = mosquitto_new(options_.client_id.c_str(), /*clean_session=*/true, this);
  if (client_ == nullptr)
    throw std::runtime_error("mqtt: cannot create the MQTT client: " + error_text(MOSQ_ERR_ERRNO));
  // publish() is called from the io thread while run() drives the socket.
  mosquitto_threaded_set(client_, true);
  mosquitto_int_option(client_, MOSQ_OPT_PROTOCOL_VERSION, MQTT_PROTOCOL_V311);
  mosquitto_int_option(client_, MOSQ_OPT_TCP_NODELAY, 1);
  if (!options_.username.empty()) {
    mosquitto_username_pw_set(client_, options_.username.c_str(),
                              options_.password.empty() ? nullptr : options_.password.c_str());
  }
  if (const auto& tls = options_.tls) {
    const bool with_certificate = !tls->certificate.empty();
    const int rc =
        mosquitto_tls_set(client_, tls->ca.c_str(), nullptr, with_certificate ? tls->certificate.c_str() : nullptr,
                          with_certificate ? tls->private_key.c_str() : nullptr, nullptr);
    if (rc != MOSQ_ERR_SUCCESS) {
      throw std::runtime_error("mqtt.tls: cannot use " + tls->ca +
                               (with_certificate ? ", " + tls->certificate + ", " + tls->private_key : std::string()) +
                               ": " + error_text(rc) + " (check that the files exist and the gateway may read them)");
    }
    // TLS 1.2 and 1.3 only; the broker's certificate must chain to `ca` and name the host.
    mosquitto_tls_opts_set(client_, 1, "tlsv1.2", nullptr);
  }
  mosquitto_connect_callback_set(client_, &MqttLink::on_connect);
  mosquitto_disconnect_callback_set(client_, &MqttLink::on_disconnect);
  mosquitto_message_callback_set(client_, &MqttLink::on_message);
  thread_ = std::thread([this] { run(); });
}

void MqttLink::run() {
  auto backoff = options_.reconnect_min;
  const auto& broker = options_.broker;
  while (!stopping_) {
    const MqttWill will = events_.will();
    mosquitto_will_set(client_, will.topic.c_str(), static_cast<int>(will.payload.size()), will.payload.data(),
                       will.qos, will.retain);
    session_lost_ = false;
    connect_sent_ = false;
    // Non-blocking connect: stop() never waits for a TCP timeout to an unreachable broker.
    int rc = mosquitto_connect_async(client_, broker.host.c_str(), broker.port,
                                     static_cast<int>(options_.keepalive.count()));
    // CONNACK, then traffic, until the session ends (on_disconnect), fails, or stop(). The CONNECT
    // is queued at once and written as soon as the transport is up, within the same loop call.
    while (rc == MOSQ_ERR_SUCCESS && !stopping_ && !session_lost_) {
      rc = mosquitto_loop(client_, 100, 1);
      if (!connect_sent_ && transport_up()) note_connect_sent();
    }
    if (rc != MOSQ_ERR_SUCCESS && !connected_) {
      const std::string reason = error_text(rc);
      if (first_time_failure(reason)) {
        spdlog::warn("mqtt: cannot connect to broker {}: {}; retrying with backoff from {} ms up to {} ms",
                     broker.to_string(), reason, options_.reconnect_min.count(), options_.reconnect_max.count());
      }
    }
    const bool was_connected = connected_.exchange(false);
    if (was_connected && restarting_.exchange(false) && !stopping_ && !closing_) {
      spdlog::info("mqtt: disconnected from broker {} on purpose; connecting again", broker.to_string());
      events_.disconnected("disconnected on purpose");
      backoff = options_.reconnect_min;
      wait_backoff(backoff);
      continue;
    }
    if (was_connected) {
      if (stopping_ || closing_) break;
      ++disconnects_;
      spdlog::warn("mqtt: lost the broker {}; reconnecting", broker.to_string());
      events_.disconnected("connection to " + broker.to_string() + " lost");
      backoff = options_.reconnect_min;
    } else {
      ++connect_failures_;
    }
    if (stopping_) break;
    wait_backoff(backoff);
    if (!was_connected) backoff = std::min(backoff * 2, options_.reconnect_max);
  }
  {
    std::lock_guard lock(mutex_);
    session_lost_ = true;
  }
  wake_.notify_all();
}

bool MqttLink::first_time_failure(const std::string& reason) {
  if (std::find(failures_logged_.begin(), failures_logged_.end(), reason) != failures_logged_.end()) return false;
  failures_logged_.push_back(reason);
  return true;
}

// Whether the connection to the broker is established (TCP connected and, with TLS, the
// handshake done): from then on the queued CONNECT has left or leaves on the next write.
bool MqttLink::transport_up() const {
  const int fd = mosquitto_socket(client_);
  if (fd < 0) return false;
  sockaddr_storage peer{};
  socklen_t length = sizeof peer;
  if (::getpeername(fd, reinterpret_cast<sockaddr*>(&peer), &length) != 0) return false;
  if (!options_.tls) return true;
  const auto* ssl = static_cast<SSL*>(mosquitto_ssl_get(client_));
  return ssl != nullptr && SSL_is_init_finished(ssl) == 1;
}

void MqttLink::note_connect_sent() {
  connect_sent_ = true;
  if (events_.connect_sent) events_.connect_sent();
}

void MqttLink::wait_backoff(std::chrono::milliseconds delay) {
  std::unique_lock lock(mutex_);
  wake_.wait_for(lock, delay, [this] { return stopping_.load(); });
}

void MqttLink::on_connect(mosquitto* client, void* self, int rc) {
  auto& link = *static_cast<MqttLink*>(self);
  if (!link.connect_sent_) link.note_connect_sent();  // a CONNACK answers a CONNECT
  if (rc != 0) {
    const std::string reason = std::string("the broker refused the connection: ") + mosquitto_connack_string(rc);
    if (link.first_time_failure(reason)) {
      spdlog::error("mqtt: {} ({}); check mqtt.username, mqtt.password_file and the broker's ACL", reason,
                    link.options_.broker.to_string());
    }
    mosquitto_disconnect(client);
    return;
  }
  for (const auto& topic : link.options_.subscriptions) mosquitto_subscribe(client, nullptr, topic.c_str(), 1);
  link.failures_logged_.clear();
  link.connected_ = true;
  ++link.connects_;
  spdlog::info("mqtt: connected to broker {} as {}", link.options_.broker.to_string(), link.options_.client_id);
  link.events_.connected();
}

void MqttLink::on_disconnect(mosquitto*, void* self, int) {
  auto& link = *static_cast<MqttLink*>(self);
  {
    std::lock_guard lock(link.mutex_);
    link.session_lost_ = true;
  }
  link.wake_.notify_all();
}

void MqttLink::on_message(mosquitto*, void* self, const mosquitto_message* message) {
  auto& link = *static_cast<MqttLink*>(self);
  ++link.received_;
  const auto* bytes = static_cast<const std::uint8_t*>(message->payload);
  link.events_.message(message->topic, protocol::Bytes(bytes, bytes + message->payloadlen));
}

bool MqttLink::publish(const std::string& topic, std::span<const std::uint8_t> payload, int qos, bool retain) {
  if (client_ == nullptr || !connected_) {
    ++publish_failures_;
    return false;
  }
  const int rc =
      mosquitto_publish(client_, nullptr, topic.c_str(), static_cast<int>(payload.size()), payload.data(), qos, retain);
  if (rc != MOSQ_ERR_SUCCESS) {
    ++publish_failures_;
    return false;
  }
  ++published_;
  return true;
}

void MqttLink::reconnect(std::optional<MqttWill> last) {
  if (client_ == nullptr || !connected_ || stopping_ || closing_) return;
  if (last) publish(last->topic, last->payload, last->qos, last->retain);
  restarting_ = true;
  mosquitto_disconnect(client_);
}

void MqttLink::stop(std::optional<MqttWill> last, std::chrono::milliseconds grace) {
  if (!thread_.joinable()) {
    if (client_ != nullptr) mosquitto_destroy(client_);
    client_ = nullptr;
    return;
  }
  if (connected_) {
    if (last) publish(last->topic, last->payload, last->qos, last->retain);
    // DISCONNECT leaves after what was queued before it; the broker then drops the will.
    closing_ = true;
    mosquitto_disconnect(client_);
    std::unique_lock lock(mutex_);
    wake_.wait_for(lock, grace, [this] { return session_lost_.load(); });
  }
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  thread_.join();
  mosquitto_destroy(client_);
  client_ = nullptr;
}

MqttLinkStats MqttLink::stats() const {
  return MqttLinkStats{connected_.load(), connects_.load(),         connect_failures_.load(), disconnects_.load(),
                       published_.load(), publish_failures_.load(), received_.load()};
}

}  // namespace sms::gateway
