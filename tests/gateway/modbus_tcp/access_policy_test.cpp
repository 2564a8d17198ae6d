// The client allow-list (IPv4/IPv6 CIDR matching, IPv4-mapped clients) and the Modbus function table.
#include <gtest/gtest.h>

#include <string>

#include "gateway/modbus_tcp/access_policy.h"

namespace sms::gateway {
namespace {

config::IpNetwork network(std::string_view text) {
  const auto parsed = config::parse_ip_network(text);
  if (!parsed) throw std::invalid_argument(parsed.error());
  return *parsed;
}

IpAddress address(std::string_view text) {
  const auto parsed = IpAddress::parse(text);
  if (!parsed) throw std::invalid_argument("not an address: " + std::string(text));
  return *parsed;
}

TEST(IpAddress, ParsesBothFamiliesAndRefusesNames) {
  EXPECT_EQ(address("192.168.10.7"), IpAddress::v4({192, 168, 10, 7}));
  EXPECT_EQ(address("fd00::1"), IpAddress::v6({0xfd, 0x00, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0x01}));
  EXPECT_FALSE(IpAddress::parse("plc.local"));
  EXPECT_FALSE(IpAddress::parse("10.0.0.0/8"));
  EXPECT_FALSE(IpAddress::parse(""));
  EXPECT_EQ(address("fd00::1").to_string(), "fd00::1");
  EXPECT_EQ(address("10.0.0.1").to_string(), "10.0.0.1");
}

TEST(IpAddress, Ipv4MappedIpv6IsUnmappedToIpv4) {
  const IpAddress mapped = IpAddress::v6({0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xFF, 0xFF, 10, 0, 0, 1});
  EXPECT_EQ(mapped.unmapped(), IpAddress::v4({10, 0, 0, 1}));
  EXPECT_EQ(address("::ffff:192.168.10.7").unmapped(), address("192.168.10.7"));
  // Not mapped: unchanged.
  EXPECT_EQ(address("fd00::1").unmapped(), address("fd00::1"));
  EXPECT_EQ(address("::1").unmapped(), address("::1"));
  EXPECT_EQ(address("10.0.0.1").unmapped(), address("10.0.0.1"));
}

TEST(IpNetworkContains, Ipv4PrefixBoundaries) {
  const auto lan = network("192.168.10.0/24");
  EXPECT_TRUE(contains(lan, address("192.168.10.0")));
  EXPECT_TRUE(contains(lan, address("192.168.10.255")));
  EXPECT_FALSE(contains(lan, address("192.168.11.0")));
  EXPECT_FALSE(contains(lan, address("192.168.9.255")));

  const auto upper_half = network("10.0.0.128/25");
  EXPECT_FALSE(contains(upper_half, address("10.0.0.127")));
  EXPECT_TRUE(contains(upper_half, address("10.0.0.128")));
  EXPECT_TRUE(contains(upper_half, address("10.0.0.255")));

  const auto odd = network("172.16.0.0/12");
  EXPECT_TRUE(contains(odd, address("172.31.255.255")));
  EXPECT_FALSE(contains(odd, address("172.32.0.0")));
  EXPECT_FALSE(contains(odd, address("172.15.255.255")));

  const auto host = network("10.0.0.7");
  EXPECT_TRUE(contains(host, address("10.0.0.7")));
  EXPECT_FALSE(contains(host, address("10.0.0.6")));
}

TEST(IpNetworkContains, Ipv6PrefixBoundaries) {
  const auto site = network("fd00:1::/64");
  EXPECT_TRUE(contains(site, address("fd00:1::1")));
  EXPECT_TRUE(contains(site, address("fd00:1::ffff:ffff:ffff:ffff")));
  EXPECT_FALSE(contains(site, address("fd00:1:0:1::")));
  EXPECT_FALSE(contains(site, address("fd00:2::1")));

  const auto ula = network("fc00::/7");
  EXPECT_TRUE(contains(ula, address("fdff::1")));
  EXPECT_TRUE(contains(ula, address("fc00::1")));
  EXPECT_FALSE(contains(ula, address("fe80::1")));

  EXPECT_TRUE(contains(network("::1"), address("::1")));
  EXPECT_FALSE(contains(network("::1"), address("::2")));
}

TEST(IpNetworkContains, ZeroPrefixIsEveryAddressOfItsFamilyOnly) {
  EXPECT_TRUE(contains(network("0.0.0.0/0"), address("255.255.255.255")));
  EXPECT_TRUE(contains(network("0.0.0.0/0"), address("0.0.0.0")));
  EXPECT_FALSE(contains(network("0.0.0.0/0"), address("::1")));
  EXPECT_TRUE(contains(network("::/0"), address("fd00::1")));
  EXPECT_FALSE(contains(network("::/0"), address("10.0.0.1")));
}

TEST(AccessPolicy, WithoutAListEveryClientIsAllowed) {
  const AccessPolicy policy;
  EXPECT_FALSE(policy.restricted());
  EXPECT_TRUE(policy.allows(address("203.0.113.9")));
  EXPECT_TRUE(policy.allows(address("2001:db8::1")));
  EXPECT_EQ(policy.describe(), "every client");
}

TEST(AccessPolicy, OnlyListedNetworksAreAllowed) {
  const AccessPolicy policy({network("192.168.10.0/24"), network("10.0.0.7"), network("fd00::/8")});
  EXPECT_TRUE(policy.restricted());
  EXPECT_TRUE(policy.allows(address("192.168.10.200")));
  EXPECT_TRUE(policy.allows(address("10.0.0.7")));
  EXPECT_TRUE(policy.allows(address("fd12:3456::1")));
  EXPECT_FALSE(policy.allows(address("10.0.0.8")));
  EXPECT_FALSE(policy.allows(address("192.168.11.1")));
  EXPECT_FALSE(policy.allows(address("2001:db8::1")));
  EXPECT_FALSE(policy.allows(address("127.0.0.1")));
  EXPECT_EQ(policy.describe(), "192.168.10.0/24, 10.0.0.7/32, fd00::/8");
}

TEST(AccessPolicy, Ipv4ClientOnADualStackListenerMatchesIpv4Entries) {
  const AccessPolicy policy({network("192.168.10.0/24")});
  EXPECT_TRUE(policy.allows(address("::ffff:192.168.10.7")));
  EXPECT_FALSE(policy.allows(address("::ffff:192.168.11.7")));
}

TEST(AccessPolicy, Ipv6EntriesDoNotMatchIpv4Clients) {
  const AccessPolicy policy({network("::/0")});
  EXPECT_TRUE(policy.allows(address("2001:db8::1")));
  EXPECT_FALSE(policy.allows(address("10.0.0.1")));
  EXPECT_FALSE(policy.allows(address("::ffff:10.0.0.1")));
}

TEST(ModbusFunctions, TableIsAscendingAndFindsByCode) {
  const auto& functions = protocol::kModbusFunctions;
  ASSERT_FALSE(functions.empty());
  for (std::size_t i = 1; i < functions.size(); ++i) EXPECT_LT(functions[i - 1].code, functions[i].code);
  const ModbusFunction* holding = find_modbus_function(0x03);
  ASSERT_NE(holding, nullptr);
  EXPECT_EQ(holding->name, "read_holding_registers");
  EXPECT_TRUE(holding->served);
  const ModbusFunction* mask = find_modbus_function(0x16);
  ASSERT_NE(mask, nullptr);
  EXPECT_EQ(mask->name, "mask_write_register");
  EXPECT_FALSE(mask->served);
  EXPECT_EQ(find_modbus_function(0x41), nullptr);
  EXPECT_EQ(find_modbus_function(0xFF), nullptr);
}

TEST(ModbusFunctions, ServedSetIsTheContractsFunctionCodes) {
  std::vector<int> served;
  for (const auto& function : protocol::kModbusFunctions) {
    if (function.served) served.push_back(function.code);
  }
  // docs/PLC_GUIDE.md "A servo unit": 01 02 03 04 05 06 15 16 23.
  EXPECT_EQ(served, (std::vector<int>{1, 2, 3, 4, 5, 6, 15, 16, 23}));
}

}  // namespace
}  // namespace sms::gateway
