#include "config/config.h"

#include <cstdlib>

#include <arpa/inet.h>

#include <algorithm>
#include <charconv>

#include "config/names.h"
#include "modbus_map/tables.h"

namespace sms::config {

std::string HostPort::to_string() const {
  const bool ipv6 = host.find(':') != std::string::npos;
  return (ipv6 ? "[" + host + "]" : host) + ":" + std::to_string(port);
}

namespace {

// "\"text\"" built by appending: GCC 12 at -O3 misreads `"\"" + std::string(...)` as an
// overlapping memcpy (-Wrestrict, GCC bug 105651).
std::string in_quotes(std::string_view text) {
  std::string quoted(1, '"');
  quoted.append(text);
  quoted.push_back('"');
  return quoted;
}

}  // namespace

Expected<HostPort> parse_host_port(std::string_view text) {
  const std::string quoted = in_quotes(text);
  std::string_view host;
  std::string_view port;
  if (text.starts_with('[')) {
    const auto close = text.find(']');
    if (close == std::string_view::npos) {
      return unexpected(quoted + " opens an IPv6 address with '[' but has no ']'");
    }
    host = text.substr(1, close - 1);
    const auto rest = text.substr(close + 1);
    if (!rest.starts_with(':')) return unexpected(quoted + " needs \":PORT\" after the ']'");
    port = rest.substr(1);
  } else {
    const auto colon = text.rfind(':');
    if (colon == std::string_view::npos) {
      return unexpected(quoted + " is not HOST:PORT (e.g. 0.0.0.0:502)");
    }
    host = text.substr(0, colon);
    port = text.substr(colon + 1);
    if (host.find(':') != std::string_view::npos) {
      return unexpected(quoted + ": an IPv6 address goes in brackets, e.g. [::]:502");
    }
  }
  if (host.empty()) return unexpected(quoted + " has no host (0.0.0.0 listens on every interface)");
  unsigned value = 0;
  const auto* end = port.data() + port.size();
  const auto [stop, error] = std::from_chars(port.data(), end, value);
  if (port.empty() || error != std::errc{} || stop != end || value > 65535) {
    return unexpected(quoted + " has no valid port (0..65535) after the ':'");
  }
  return HostPort{std::string(host), static_cast<std::uint16_t>(value)};
}

namespace {

constexpr std::string_view kNetworkForm =
    "write ADDRESS/PREFIX (e.g. 192.168.10.0/24, fd00::/8) or one address (10.0.0.7, ::1)";

int family_code(IpNetwork::Family family) { return family == IpNetwork::Family::V4 ? AF_INET : AF_INET6; }

// Clears the bits below the prefix; true when any was set.
bool clear_host_bits(IpNetwork& network) {
  bool any = false;
  for (std::size_t i = 0; i < network.address.size(); ++i) {
    const std::size_t first_bit = i * 8;
    std::uint8_t keep = 0xFF;
    if (first_bit >= network.prefix_length) {
      keep = 0;
    } else if (network.prefix_length - first_bit < 8) {
      keep = static_cast<std::uint8_t>(0xFF << (8 - (network.prefix_length - first_bit)));
    }
    any = any || (network.address[i] & ~keep) != 0;
    network.address[i] &= keep;
  }
  return any;
}

}  // namespace

std::string IpNetwork::to_string() const {
  char text[INET6_ADDRSTRLEN] = {};
  ::inet_ntop(family_code(family), address.data(), text, sizeof text);
  return std::string(text) + "/" + std::to_string(prefix_length);
}

Expected<IpNetwork> parse_ip_network(std::string_view text) {
  const std::string quoted = in_quotes(text);
  const auto slash = text.find('/');
  const std::string address_text(text.substr(0, slash));
  IpNetwork network;
  network.family = address_text.find(':') != std::string::npos ? IpNetwork::Family::V6 : IpNetwork::Family::V4;
  const bool v4 = network.family == IpNetwork::Family::V4;
  if (::inet_pton(family_code(network.family), address_text.c_str(), network.address.data()) != 1) {
    return unexpected(quoted + " is not an IPv4 or IPv6 address; " + std::string(kNetworkForm));
  }
  const unsigned max_prefix = v4 ? 32 : 128;
  network.prefix_length = static_cast<std::uint8_t>(max_prefix);
  if (slash != std::string_view::npos) {
    const auto prefix = text.substr(slash + 1);
    unsigned value = 0;
    const auto* end = prefix.data() + prefix.size();
    const auto [stop, error] = std::from_chars(prefix.data(), end, value);
    if (prefix.empty() || error != std::errc{} || stop != end || value > max_prefix) {
      return unexpected(quoted + ": the prefix length after '/' must be 0.." + std::to_string(max_prefix) + " for an " +
                        (v4 ? "IPv4" : "IPv6") + " network");
    }
    network.prefix_length = static_cast<std::uint8_t>(value);
  }
  IpNetwork cleared = network;
  if (clear_host_bits(cleared)) {
    return unexpected(quoted + " has address bits set below its /" + std::to_string(network.prefix_length) +
                      " prefix; the network is " + cleared.to_string() + " (or give /" + std::to_string(max_prefix) +
                      " for the one address)");
  }
  return network;
}

std::string FrameGap::to_string() const {
  switch (kind) {
    case Kind::Spec: return "spec";
    case Kind::Characters: return "3.5chars";
    case Kind::Fixed: return std::to_string(fixed.count()) + "us";
  }
  return "spec";
}

Expected<FrameGap> parse_frame_gap(std::string_view text) {
  if (text == "spec") return FrameGap{};
  if (text == "3.5chars") return FrameGap{FrameGap::Kind::Characters, {}};
  constexpr std::string_view kMicros = "us";
  constexpr long kMaxMicros = 1'000'000;
  if (text.size() > kMicros.size() && text.substr(text.size() - kMicros.size()) == kMicros) {
    const std::string_view digits = text.substr(0, text.size() - kMicros.size());
    long value = 0;
    const auto [end, error] = std::from_chars(digits.data(), digits.data() + digits.size(), value);
    if (error == std::errc{} && end == digits.data() + digits.size() && value >= 0 && value <= kMaxMicros) {
      return FrameGap{FrameGap::Kind::Fixed, std::chrono::microseconds{value}};
    }
  }
  return unexpected(in_quotes(text) +
                    " is not a frame gap; write spec (3.5 characters, 1.75 ms above 19200 "
                    "bit/s), 3.5chars (3.5 characters at every rate) or a time such as 500us "
                    "(0us..1000000us)");
}

modbus_map::ByteOrder effective_byte_order(const ServoConfig& servo) {
  if (servo.byte_order) return *servo.byte_order;
  if (!servo.table) return modbus_map::ByteOrder::HighFirst;  // Modbus registers
  return modbus_map::table(*servo.table).default_byte_order;
}

modbus_map::StopAction effective_safe_stop(const ServoConfig& servo) {
  if (!servo.table) return modbus_map::StopAction::None;
  if (servo.safe_stop) return *servo.safe_stop;
  return modbus_map::motion_spec(*servo.table).default_stop;
}

std::optional<std::int32_t> effective_stop_deceleration(const Config& config, const ServoConfig& servo) {
  if (servo.stop_deceleration) return servo.stop_deceleration;
  if (servo.bus_index < config.buses.size()) return config.buses[servo.bus_index].stop_deceleration;
  return std::nullopt;
}

const BusConfig* find_bus(const Config& config, std::string_view name) {
  for (const auto& bus : config.buses) {
    if (bus.name == name) return &bus;
  }
  return nullptr;
}

const ServoConfig* find_unit(const Config& config, std::uint8_t unit_id) {
  for (const auto& servo : config.servos) {
    if (servo.unit_id == unit_id) return &servo;
  }
  return nullptr;
}

std::string_view to_string(Parity parity) { return detail::name_of(detail::kParityNames, parity); }
std::string_view to_string(RtsMode rts) { return detail::name_of(detail::kRtsNames, rts); }
std::string_view to_string(Profile profile) { return detail::name_of(detail::kProfileNames, profile); }
std::string_view to_string(LogLevel level) { return detail::name_of(detail::kLogLevelNames, level); }
std::string_view to_string(LogFormat format) { return detail::name_of(detail::kLogFormatNames, format); }
std::string_view to_string(modbus_map::ByteOrder order) { return detail::name_of(detail::kByteOrderNames, order); }
std::string_view to_string(WatchdogFeed feed) { return detail::name_of(detail::kWatchdogFeedNames, feed); }
std::string_view to_string(StartAction action) { return detail::name_of(detail::kStartActionNames, action); }
std::string_view to_string(Role role) { return detail::name_of(detail::kRoleNames, role); }
std::string_view to_string(RtuEcho echo) { return detail::name_of(detail::kRtuEchoNames, echo); }
std::optional<Role> role_from_name(std::string_view name) { return detail::value_of(detail::kRoleNames, name); }

}  // namespace sms::config

namespace sms::config {

std::string sparkplug_device_id(const ServoConfig& servo) {
  return servo.name.empty() ? "unit-" + std::to_string(servo.unit_id) : servo.name;
}

std::chrono::milliseconds worst_transaction(const BusConfig& bus) {
  constexpr std::uint64_t kLongestExchangeBytes = std::uint64_t{2} * 256;
  const std::uint64_t bits_per_byte = 1 + 8 + (bus.parity == Parity::None ? 0 : 1) + bus.stop_bits;
  const std::uint64_t wire_us =
      bus.baud == 0 ? 0 : (kLongestExchangeBytes * bits_per_byte * std::uint64_t{1000000} + bus.baud - 1) / bus.baud;
  const auto per_attempt = bus.response_timeout + std::chrono::milliseconds{(wire_us + 999) / 1000};
  return per_attempt * (2 * (1 + bus.retries));
}

std::chrono::milliseconds effective_probe_period(const BusConfig& bus) {
  if (bus.protocol != protocol::BusProtocol::D55d) return bus.offline_probe_period;
  return std::min(bus.offline_probe_period, kD55dKeepAlive);
}

std::optional<std::chrono::milliseconds> d55d_instruction_gap(const BusConfig& bus) {
  if (bus.protocol != protocol::BusProtocol::D55d) return std::nullopt;
  return bus.poll_period + worst_transaction(bus);
}

std::string effective_state_dir(const Config& config) {
  if (!config.state_dir.empty()) return config.state_dir;
  const char* systemd = std::getenv("STATE_DIRECTORY");  // may list several, ':'-separated
  if (systemd == nullptr) return {};
  const std::string_view dirs(systemd);
  return std::string(dirs.substr(0, dirs.find(':')));
}

}  // namespace sms::config

namespace sms::config {

Expected<RtuSlaveConfig> parse_rtu_slave_option(std::string_view text) {
  const std::string form = "expected DEVICE[:BAUD[:PARITY]], e.g. /dev/ttyUSB1:19200:even (parity none, even or odd)";
  RtuSlaveConfig port;
  // From the right: /dev/serial/by-path names have colons of their own.
  std::string_view rest = text;
  const auto last_part = [&]() -> std::string_view {
    const auto colon = rest.rfind(':');
    return colon == std::string_view::npos ? std::string_view{} : rest.substr(colon + 1);
  };
  const auto drop_last_part = [&] { rest = rest.substr(0, rest.rfind(':')); };
  if (const auto parity = detail::value_of(detail::kParityNames, last_part())) {
    port.parity = *parity;
    drop_last_part();
    const auto baud_text = last_part();
    std::uint32_t baud = 0;
    const auto [end, error] = std::from_chars(baud_text.data(), baud_text.data() + baud_text.size(), baud);
    if (baud_text.empty() || error != std::errc{} || end != baud_text.data() + baud_text.size()) {
      return unexpected("`" + std::string(text) + "`: a parity needs a rate before it; " + form);
    }
    port.baud = baud;
    drop_last_part();
  } else if (const auto baud_text = last_part();
             !baud_text.empty() &&
             std::all_of(baud_text.begin(), baud_text.end(), [](char c) { return c >= '0' && c <= '9'; })) {
    // Only digits: a rate (a by-path device name ends in "...:1.0-port0", which is not one).
    std::uint32_t baud = 0;
    const auto [end, error] = std::from_chars(baud_text.data(), baud_text.data() + baud_text.size(), baud);
    if (error != std::errc{})
      return unexpected("`" + std::string(text) + "`: `" + std::string(baud_text) + "` is not a rate; " + form);
    port.baud = baud;
    drop_last_part();
  }
  if (rest.empty()) return unexpected("`" + std::string(text) + "`: no device; " + form);
  if (port.baud < kMinRtuSlaveBaud || port.baud > kMaxRtuSlaveBaud) {
    return unexpected("`" + std::string(text) + "`: " + std::to_string(port.baud) + " bit/s is outside " +
                      std::to_string(kMinRtuSlaveBaud) + ".." + std::to_string(kMaxRtuSlaveBaud));
  }
  port.device = std::string(rest);
  return port;
}

std::optional<std::string> rtu_slave_conflict(const Config& config, const RtuSlaveConfig& port) {
  for (const auto& bus : config.buses) {
    if (bus.device == port.device) {
      return port.device + " is the device of bus `" + bus.name +
             "`; an upstream port needs a serial line of its own (a second adapter)";
    }
  }
  for (std::size_t i = 0; i < config.modbus_rtu_slave.size(); ++i) {
    if (config.modbus_rtu_slave[i].device == port.device) {
      return port.device + " is already modbus_rtu_slave[" + std::to_string(i) + "]'s device";
    }
  }
  return std::nullopt;
}

}  // namespace sms::config

namespace sms::config {

bool is_loopback_host(std::string_view host) {
  if (host.starts_with('[') && host.ends_with(']')) host = host.substr(1, host.size() - 2);
  if (host.starts_with("::ffff:")) host.remove_prefix(7);  // an IPv4 address in IPv6 form
  return host == "localhost" || host == "::1" || host.starts_with("127.");
}

std::optional<std::string> console_listen_problem(const ConsoleConfig& console) {
  if (is_loopback_host(console.listen.host)) return std::nullopt;
  const std::string where = console.listen.to_string();
  if (console.users.empty() && !console.tls) {
    return where +
           " is reachable from other machines, but with neither users nor tls the console has no way to know "
           "who asks; it serves read-only on a loopback address only. Add users (password_hash from "
           "`sms-gateway hash-password`) or tls: true, or listen on 127.0.0.1";
  }
  if (!console.users.empty() && !console.https() && !console.insecure_http) {
    return where +
           " is reachable from other machines and the console's users log in with passwords, which plain "
           "HTTP would carry in clear across the network: give the console a certificate and key "
           "(console.certificate and console.key; the Debian package makes a self-signed pair in "
           "/etc/sms-gateway/console/), or tls: true with modbus_tcp.tls, or listen on 127.0.0.1. "
           "insecure_http: true serves plain HTTP anyway (a warning at every start)";
  }
  return std::nullopt;
}

}  // namespace sms::config
