#pragma once
// MQTT test parts: a real Mosquitto broker (Debian's /usr/sbin/mosquitto) on an ephemeral
// loopback port, a Sparkplug host stand-in that records every message under spBv1.0/#
// (decoded with protocol/sparkplug, and kept as bytes for protoc) and publishes commands and
// its STATE, and protoc's reading of a payload's metrics.
#include <mosquitto.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "protocol/sparkplug/sparkplug.h"
#include "tests/support/eventually.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

struct SparkplugMessage {
  sparkplug::Topic topic;
  sparkplug::Payload payload;
  std::chrono::steady_clock::time_point arrived;
  std::vector<std::uint8_t> bytes;  // as published

  const sparkplug::Metric* metric(const std::string& name) const {
    for (const auto& m : payload.metrics) {
      if (m.name == name) return &m;
    }
    return nullptr;
  }
};

struct HostOptions {
  std::string username, password, ca;  // ca: TLS when set
};

class SparkplugHost {
 public:
  explicit SparkplugHost(std::uint16_t port, HostOptions options = {}) {
    mosquitto_lib_init();
    client_ = mosquitto_new(nullptr, true, this);
    if (!options.username.empty())
      mosquitto_username_pw_set(client_, options.username.c_str(), options.password.c_str());
    if (!options.ca.empty()) mosquitto_tls_set(client_, options.ca.c_str(), nullptr, nullptr, nullptr, nullptr);
    mosquitto_connect_callback_set(client_, [](mosquitto* c, void* self, int rc) {
      if (rc == 0) mosquitto_subscribe(c, nullptr, "spBv1.0/#", 1);
      static_cast<SparkplugHost*>(self)->subscribed_ = rc == 0;
    });
    mosquitto_message_callback_set(client_, [](mosquitto*, void* self, const mosquitto_message* message) {
      static_cast<SparkplugHost*>(self)->record(message);
    });
    if (mosquitto_connect(client_, "localhost", port, 30) != MOSQ_ERR_SUCCESS)
      throw std::runtime_error("host: cannot connect");
    mosquitto_loop_start(client_);
    if (!eventually([&] { return subscribed_.load(); })) throw std::runtime_error("host: not subscribed");
    std::this_thread::sleep_for(100ms);  // SUBACK
  }
  ~SparkplugHost() {
    mosquitto_disconnect(client_);
    mosquitto_loop_stop(client_, true);
    mosquitto_destroy(client_);
  }

  // The first message since `from` (an index into everything received) that `match` accepts.
  std::optional<SparkplugMessage> wait(std::function<bool(const SparkplugMessage&)> match,
                                       std::chrono::milliseconds timeout = 10s, std::size_t from = 0) {
    std::unique_lock lock(mutex_);
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    for (std::size_t i = from;;) {
      for (; i < messages_.size(); ++i) {
        if (match(messages_[i])) return messages_[i];
      }
      if (changed_.wait_until(lock, deadline) == std::cv_status::timeout && i == messages_.size()) return std::nullopt;
    }
  }
  std::size_t count() {
    std::lock_guard lock(mutex_);
    return messages_.size();
  }
  std::string summary() {
    std::lock_guard lock(mutex_);
    std::string text;
    for (const auto& m : messages_)
      text += sparkplug::topic_text(m.topic) + " (" + std::to_string(m.payload.metrics.size()) + " metrics)\n";
    return text;
  }

  void command(sparkplug::MessageType type, const std::string& group, const std::string& node,
               const std::string& device, std::vector<sparkplug::Metric> metrics) {
    sparkplug::Payload payload;
    payload.timestamp = 1;
    payload.metrics = std::move(metrics);
    raw(sparkplug::topic_text({group, type, node, device}), sparkplug::encode(payload));
  }
  void raw(const std::string& topic, const std::vector<std::uint8_t>& bytes, bool retain = false) {
    mosquitto_publish(client_, nullptr, topic.c_str(), static_cast<int>(bytes.size()), bytes.data(), 1, retain);
  }
  // The host's STATE as a Sparkplug 3.0 host application publishes it: retained, QoS 1.
  void state(const std::string& host_id, bool online, std::uint64_t timestamp) {
    const std::string json = sparkplug::host_state_json({online, timestamp});
    raw(sparkplug::state_topic(host_id), std::vector<std::uint8_t>(json.begin(), json.end()), true);
  }

 private:
  void record(const mosquitto_message* message) {
    const auto topic = sparkplug::parse_topic(message->topic);
    if (!topic) return;
    const auto* bytes = static_cast<const std::uint8_t*>(message->payload);
    const auto payload =
        sparkplug::decode(std::span<const std::uint8_t>(bytes, static_cast<std::size_t>(message->payloadlen)));
    if (!payload) return;
    std::lock_guard lock(mutex_);
    messages_.push_back(SparkplugMessage{*topic, *payload, std::chrono::steady_clock::now(),
                                         std::vector<std::uint8_t>(bytes, bytes + message->payloadlen)});
    changed_.notify_all();
  }

  mosquitto* client_ = nullptr;
  std::atomic<bool> subscribed_{false};
  std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<SparkplugMessage> messages_;
};

// A payload's metrics as `protoc --decode` reads them with the Sparkplug B .proto: for each
// metric its fields by name ("name", "timestamp", "datatype", "int_value", "long_value", ...),
// values as protoc prints them (strings keep their quotes). Properties are left out. Throws when
// protoc refuses the bytes.
using ProtocMetric = std::map<std::string, std::string>;
inline std::vector<ProtocMetric> protoc_metrics(const std::vector<std::uint8_t>& bytes, const TempDir& dir) {
  static int count = 0;
  const std::string in = dir.file("payload-" + std::to_string(++count) + ".bin");
  std::ofstream(in, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  const std::string command = std::string(SMS_PROTOC) + " --proto_path=" + SMS_SOURCE_DIR +
                              "/protocol/sparkplug --decode=sms.sparkplug.wire.Payload sparkplug_b.proto < " + in;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) throw std::runtime_error("cannot run " + command);
  std::string text;
  std::array<char, 512> buffer{};
  while (fgets(buffer.data(), buffer.size(), pipe)) text += buffer.data();
  if (pclose(pipe) != 0) throw std::runtime_error(command + " failed:\n" + text);
  std::vector<ProtocMetric> metrics;
  std::istringstream lines(text);
  int depth = 0;
  for (std::string line; std::getline(lines, line);) {
    const auto first = line.find_first_not_of(' ');
    if (first == std::string::npos) continue;
    const std::string content = line.substr(first);
    if (content == "}") {
      --depth;
      continue;
    }
    if (content.back() == '{') {
      if (depth == 0 && content == "metrics {") metrics.emplace_back();
      ++depth;
      continue;
    }
    const auto colon = content.find(": ");
    if (depth == 1 && colon != std::string::npos && !metrics.empty()) {
      metrics.back()[content.substr(0, colon)] = content.substr(colon + 2);
    }
  }
  return metrics;
}

inline std::function<bool(const SparkplugMessage&)> is(sparkplug::MessageType type, const std::string& device = "") {
  return [type, device](const SparkplugMessage& m) { return m.topic.type == type && m.topic.device == device; };
}

}  // namespace sms::e2e
