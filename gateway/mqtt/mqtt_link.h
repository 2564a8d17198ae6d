#pragma once
// One MQTT 3.1.1 client connection to a broker (libmosquitto from Debian), on a thread of its
// own: connects, keeps the session alive, reconnects with exponential backoff (reconnect_min ..
// reconnect_max) when the broker goes away, and hands what happens to its owner. It knows
// nothing of Sparkplug: the owner (SparkplugNode) gives the will before each connection attempt
// (its NDEATH with the next bdSeq), the topics to subscribe and what to publish, and learns when
// an attempt's CONNECT went out (the bdSeq is then used up; a refused TCP connection uses none).
//
//   MqttLink link(options, events);    // events run on the link's thread
//   link.start();
//   link.publish(topic, bytes, 0);     // any thread; false while not connected
//   link.stop();                       // disconnects cleanly (no will) and joins
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "config/config.h"
#include "gateway/mqtt/mqtt_stats.h"
#include "protocol/packet.h"

struct mosquitto;
struct mosquitto_message;

namespace sms::gateway {

struct MqttLinkOptions {
  config::HostPort broker;
  std::string client_id;
  std::string username;                      // empty: none
  std::string password;                      // with username
  std::optional<config::MqttTlsConfig> tls;  // empty: plain TCP
  std::chrono::seconds keepalive{30};
  std::chrono::milliseconds reconnect_min{500};
  std::chrono::milliseconds reconnect_max{30000};
  std::vector<std::string> subscriptions;  // subscribed at QoS 1 after every connection
};

struct MqttWill {
  std::string topic;
  protocol::Bytes payload;
  int qos = 1;
  bool retain = false;
};

class MqttLink {
 public:
  struct Events {
    std::function<MqttWill()> will;  // before each connection attempt
    // The attempt's CONNECT went out (the transport came up): at most once per attempt, before
    // `connected`. An attempt that never reached the broker (refused, unreachable, failed TLS
    // handshake) does not call it.
    std::function<void()> connect_sent;
    std::function<void()> connected;                              // session up, subscriptions sent
    std::function<void(const std::string& reason)> disconnected;  // session lost
    std::function<void(std::string topic, protocol::Bytes payload)> message;
  };

  MqttLink(MqttLinkOptions options, Events events);
  ~MqttLink();  // stop()
  MqttLink(const MqttLink&) = delete;
  MqttLink& operator=(const MqttLink&) = delete;

  // Throws std::runtime_error when the client cannot be set up (TLS files unreadable, ...).
  void start();
  // When connected: `last` (if any) is published, then DISCONNECT; waits up to `grace` for it
  // to leave. Then ends the thread. Idempotent.
  void stop(std::optional<MqttWill> last = std::nullopt, std::chrono::milliseconds grace = std::chrono::seconds{1});

  // Any thread, when connected: publishes `last`, sends DISCONNECT, and connects again after
  // reconnect_min (with a new will). Not counted as a lost session.
  void reconnect(std::optional<MqttWill> last);

  bool publish(const std::string& topic, std::span<const std::uint8_t> payload, int qos, bool retain = false);
  bool connected() const { return connected_.load(); }
  MqttLinkStats stats() const;

 private:
  void run();
  void wait_backoff(std::chrono::milliseconds delay);
  bool transport_up() const;
  void note_connect_sent();
  static void on_connect(mosquitto* client, void* self, int rc);
  static void on_disconnect(mosquitto* client, void* self, int rc);
  static void on_message(mosquitto* client, void* self, const mosquitto_message* message);

  MqttLinkOptions options_;
  Events events_;
  mosquitto* client_ = nullptr;
  std::thread thread_;
  std::atomic<bool> stopping_{false};
  std::atomic<bool> closing_{false};     // stop() sent DISCONNECT: the session's end is not a loss
  std::atomic<bool> restarting_{false};  // reconnect() sent DISCONNECT: connect again
  bool connect_sent_ = false;            // this attempt's CONNECT went out (link thread)
  std::atomic<bool> connected_{false};
  std::atomic<bool> session_lost_{false};
  std::mutex mutex_;  // backoff wait and stop
  std::condition_variable wake_;
  // The reasons logged since the last session: each is logged once per outage, so a broker that
  // stays away (or alternates between refusing and resetting) does not fill the log.
  bool first_time_failure(const std::string& reason);
  std::vector<std::string> failures_logged_;
  std::atomic<std::uint64_t> connects_{0}, connect_failures_{0}, disconnects_{0}, published_{0}, publish_failures_{0},
      received_{0};
};

}  // namespace sms::gateway
