#include "config/config.h"

#include <charconv>

#include "config/names.h"
#include "modbus_map/tables.h"

namespace sms::config {

std::string HostPort::to_string() const {
  const bool ipv6 = host.find(':') != std::string::npos;
  return (ipv6 ? "[" + host + "]" : host) + ":" + std::to_string(port);
}

Expected<HostPort> parse_host_port(std::string_view text) {
  const std::string quoted = "\"" + std::string(text) + "\"";
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

modbus_map::ByteOrder effective_byte_order(const ServoConfig& servo) {
  if (servo.byte_order) return *servo.byte_order;
  if (!servo.table) return modbus_map::ByteOrder::HighFirst;  // Modbus registers
  return modbus_map::table(*servo.table).default_byte_order;
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
std::string_view to_string(modbus_map::ByteOrder order) {
  return detail::name_of(detail::kByteOrderNames, order);
}

}  // namespace sms::config
