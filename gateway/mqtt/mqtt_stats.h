#pragma once
// What the MQTT Sparkplug B side counts, for /metrics (metrics.h) without its headers.
#include <array>
#include <cstddef>
#include <cstdint>

namespace sms::gateway {

struct MqttLinkStats {
  bool connected = false;
  std::uint64_t connects = 0;          // sessions established (CONNACK accepted)
  std::uint64_t connect_failures = 0;  // attempts that did not get a session
  std::uint64_t disconnects = 0;       // sessions lost (not counting stop())
  std::uint64_t published = 0;
  std::uint64_t publish_failures = 0;  // publish() while not connected, or refused by the library
  std::uint64_t received = 0;
};

struct SparkplugStats {
  MqttLinkStats link;
  std::array<std::uint64_t, 9> published{};  // by sparkplug::MessageType
  std::uint64_t commands_ok = 0;
  std::uint64_t commands_refused = 0;  // unknown metric, read-only, bad value, role, exception, queue full
  std::uint64_t bad_messages = 0;      // not a Sparkplug payload, unknown device
  std::size_t devices_online = 0;      // born devices
  std::size_t devices = 0;
};

}  // namespace sms::gateway
