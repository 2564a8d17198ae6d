#include "gateway/modbus_tcp/access_policy.h"

#include <arpa/inet.h>

#include <algorithm>

namespace sms::gateway {
namespace {

using Family = config::IpNetwork::Family;

// ::ffff:0:0/96 (RFC 4291 §2.5.5.2): an IPv4 address as seen on an IPv6 socket.
constexpr std::array<std::uint8_t, 12> kV4MappedPrefix{0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xFF, 0xFF};

}  // namespace

IpAddress IpAddress::v4(const std::array<std::uint8_t, 4>& bytes) {
  IpAddress address;
  address.family = Family::V4;
  std::copy(bytes.begin(), bytes.end(), address.bytes.begin());
  return address;
}

IpAddress IpAddress::v6(const std::array<std::uint8_t, 16>& bytes) {
  IpAddress address;
  address.family = Family::V6;
  address.bytes = bytes;
  return address;
}

std::optional<IpAddress> IpAddress::parse(std::string_view text) {
  const std::string copy(text);
  IpAddress address;
  address.family = copy.find(':') != std::string::npos ? Family::V6 : Family::V4;
  const int af = address.family == Family::V4 ? AF_INET : AF_INET6;
  if (::inet_pton(af, copy.c_str(), address.bytes.data()) != 1) return std::nullopt;
  return address;
}

IpAddress IpAddress::unmapped() const {
  if (family != Family::V6 || !std::equal(kV4MappedPrefix.begin(), kV4MappedPrefix.end(), bytes.begin())) {
    return *this;
  }
  return v4({bytes[12], bytes[13], bytes[14], bytes[15]});
}

std::string IpAddress::to_string() const {
  char text[INET6_ADDRSTRLEN] = {};
  ::inet_ntop(family == Family::V4 ? AF_INET : AF_INET6, bytes.data(), text, sizeof text);
  return text;
}

bool contains(const config::IpNetwork& network, const IpAddress& address) {
  if (network.family != address.family) return false;
  const std::size_t whole_bytes = network.prefix_length / 8;
  if (!std::equal(network.address.begin(), network.address.begin() + static_cast<std::ptrdiff_t>(whole_bytes),
                  address.bytes.begin())) {
    return false;
  }
  const unsigned rest_bits = network.prefix_length % 8;
  if (rest_bits == 0) return true;
  const auto mask = static_cast<std::uint8_t>(0xFF << (8 - rest_bits));
  return (network.address[whole_bytes] & mask) == (address.bytes[whole_bytes] & mask);
}

AccessPolicy::AccessPolicy(std::vector<config::IpNetwork> allow) : allow_(std::move(allow)) {}

bool AccessPolicy::allows(const IpAddress& address) const {
  if (allow_.empty()) return true;
  const IpAddress client = address.unmapped();
  return std::any_of(allow_.begin(), allow_.end(),
                     [&](const config::IpNetwork& network) { return contains(network, client); });
}

std::string AccessPolicy::describe() const {
  if (allow_.empty()) return "every client";
  std::string text;
  for (const auto& network : allow_) {
    if (!text.empty()) text += ", ";
    text += network.to_string();
  }
  return text;
}

}  // namespace sms::gateway
