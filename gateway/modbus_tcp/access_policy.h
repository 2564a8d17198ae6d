#pragma once
// Who may talk to the gateway over Modbus TCP. Modbus has no authentication, so the gateway's
// access control is the bind address, this client allow-list (modbus_tcp.allow), read-only units
// (servos[].read_only: read_only_refusal() in gateway/service/role_policy.h) and, with Modbus/TCP
// Security, the certificate's role. Pure: no sockets, no Asio.
//
//   AccessPolicy policy(config.modbus_tcp.allow);
//   if (!policy.allows(client_address)) { close the connection; }
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "protocol/modbus_pdu.h"

namespace sms::gateway {

// A client's address as the socket reports it.
struct IpAddress {
  config::IpNetwork::Family family = config::IpNetwork::Family::V4;
  std::array<std::uint8_t, 16> bytes{};  // network byte order; IPv4 uses the first 4 bytes

  static IpAddress v4(const std::array<std::uint8_t, 4>& bytes);
  static IpAddress v6(const std::array<std::uint8_t, 16>& bytes);
  // "192.168.10.7", "fd00::1", "::ffff:10.0.0.1"; nullopt for anything else.
  static std::optional<IpAddress> parse(std::string_view text);

  // An IPv4 client on a dual-stack IPv6 listener arrives as ::ffff:a.b.c.d: that is a.b.c.d.
  IpAddress unmapped() const;
  std::string to_string() const;
  friend bool operator==(const IpAddress&, const IpAddress&) = default;
};

// True when `address` lies in `network` (families must match; see IpAddress::unmapped()).
bool contains(const config::IpNetwork& network, const IpAddress& address);

class AccessPolicy {
 public:
  AccessPolicy() = default;  // every client
  explicit AccessPolicy(std::vector<config::IpNetwork> allow);

  // True when no allow-list is configured, or the (unmapped) address is in one of its networks.
  bool allows(const IpAddress& address) const;
  bool restricted() const { return !allow_.empty(); }
  // For the startup log line: "every client" or "192.168.10.0/24, fd00::/8".
  std::string describe() const;

 private:
  std::vector<config::IpNetwork> allow_;
};

// The Modbus function table lives in protocol/modbus_pdu.h.
using protocol::find_modbus_function;
using protocol::function_effect;
using protocol::FunctionEffect;
using protocol::ModbusFunction;

}  // namespace sms::gateway
