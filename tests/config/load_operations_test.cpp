// The operations and security keys: modbus_tcp.allow (client networks) and logging.format,
// with every rejection's message and place, and the CIDR parser they rest on.
#include <gtest/gtest.h>

#include <string>
#include <string_view>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;
using testing::kBusAndServo;

Config load_or_fail(const std::string& yaml) {
  auto config = load_config_string(yaml, "plant.yaml");
  if (!config) {
    ADD_FAILURE() << config.error().to_string();
    return {};
  }
  return std::move(*config);
}

// ---- parse_ip_network ----

TEST(IpNetworkParse, Ipv4NetworkAndSingleAddress) {
  const auto network = parse_ip_network("192.168.10.0/24");
  ASSERT_TRUE(network) << network.error();
  EXPECT_EQ(network->family, IpNetwork::Family::V4);
  EXPECT_EQ(network->prefix_length, 24);
  const std::array<std::uint8_t, 16> bytes{192, 168, 10, 0};
  EXPECT_EQ(network->address, bytes);
  EXPECT_EQ(network->to_string(), "192.168.10.0/24");

  const auto host = parse_ip_network("10.0.0.7");
  ASSERT_TRUE(host) << host.error();
  EXPECT_EQ(host->prefix_length, 32);
  EXPECT_EQ(host->to_string(), "10.0.0.7/32");
}

TEST(IpNetworkParse, Ipv6NetworkAndSingleAddress) {
  const auto network = parse_ip_network("fd00:1::/64");
  ASSERT_TRUE(network) << network.error();
  EXPECT_EQ(network->family, IpNetwork::Family::V6);
  EXPECT_EQ(network->prefix_length, 64);
  const std::array<std::uint8_t, 16> bytes{0xfd, 0x00, 0x00, 0x01};
  EXPECT_EQ(network->address, bytes);
  EXPECT_EQ(network->to_string(), "fd00:1::/64");

  const auto loopback = parse_ip_network("::1");
  ASSERT_TRUE(loopback) << loopback.error();
  EXPECT_EQ(loopback->prefix_length, 128);
  EXPECT_EQ(loopback->address[15], 1);
  EXPECT_EQ(loopback->to_string(), "::1/128");
}

TEST(IpNetworkParse, PrefixZeroIsEveryAddress) {
  const auto all = parse_ip_network("0.0.0.0/0");
  ASSERT_TRUE(all) << all.error();
  EXPECT_EQ(all->prefix_length, 0);
  const auto all6 = parse_ip_network("::/0");
  ASSERT_TRUE(all6) << all6.error();
  EXPECT_EQ(all6->prefix_length, 0);
}

TEST(IpNetworkParse, RefusesWhatIsNotANetwork) {
  constexpr std::string_view kForm =
      "write ADDRESS/PREFIX (e.g. 192.168.10.0/24, fd00::/8) or one address (10.0.0.7, ::1)";
  EXPECT_EQ(parse_ip_network("plc.local").error(),
            "\"plc.local\" is not an IPv4 or IPv6 address; " + std::string(kForm));
  EXPECT_EQ(parse_ip_network("10.0.0/8").error(), "\"10.0.0/8\" is not an IPv4 or IPv6 address; " + std::string(kForm));
  EXPECT_EQ(parse_ip_network("").error(), "\"\" is not an IPv4 or IPv6 address; " + std::string(kForm));
  EXPECT_EQ(parse_ip_network("[::1]/128").error(),
            "\"[::1]/128\" is not an IPv4 or IPv6 address; " + std::string(kForm));
  EXPECT_EQ(parse_ip_network("10.0.0.0/33").error(),
            "\"10.0.0.0/33\": the prefix length after '/' must be 0..32 for an IPv4 network");
  EXPECT_EQ(parse_ip_network("10.0.0.0/").error(),
            "\"10.0.0.0/\": the prefix length after '/' must be 0..32 for an IPv4 network");
  EXPECT_EQ(parse_ip_network("10.0.0.0/+8").error(),
            "\"10.0.0.0/+8\": the prefix length after '/' must be 0..32 for an IPv4 network");
  EXPECT_EQ(parse_ip_network("fd00::/129").error(),
            "\"fd00::/129\": the prefix length after '/' must be 0..128 for an IPv6 network");
}

TEST(IpNetworkParse, RefusesHostBitsBelowThePrefixAndNamesTheNetwork) {
  EXPECT_EQ(parse_ip_network("192.168.10.5/24").error(),
            "\"192.168.10.5/24\" has address bits set below its /24 prefix; the network is 192.168.10.0/24 (or "
            "give /32 for the one address)");
  EXPECT_EQ(parse_ip_network("10.0.0.128/25").has_value(), true);
  EXPECT_EQ(parse_ip_network("10.0.0.129/25").error(),
            "\"10.0.0.129/25\" has address bits set below its /25 prefix; the network is 10.0.0.128/25 (or give /32 "
            "for the one address)");
  EXPECT_EQ(parse_ip_network("fd00::1/64").error(),
            "\"fd00::1/64\" has address bits set below its /64 prefix; the network is fd00::/64 (or give /128 for "
            "the one address)");
}

// ---- modbus_tcp.allow ----

TEST(ConfigOperations, AllowListIsReadInOrder) {
  const Config config = load_or_fail(R"(modbus_tcp:
  allow:
    - 192.168.10.0/24
    - "fd00::/8"
    - 127.0.0.1
)" + kBusAndServo);
  ASSERT_EQ(config.modbus_tcp.allow.size(), 3u);
  EXPECT_EQ(config.modbus_tcp.allow[0].to_string(), "192.168.10.0/24");
  EXPECT_EQ(config.modbus_tcp.allow[1].to_string(), "fd00::/8");
  EXPECT_EQ(config.modbus_tcp.allow[2].to_string(), "127.0.0.1/32");
}

TEST(ConfigOperations, WithoutAllowEveryClientMayConnect) {
  const Config config = load_or_fail(kBusAndServo);
  EXPECT_TRUE(config.modbus_tcp.allow.empty());
  EXPECT_EQ(config.logging.format, LogFormat::Plain);
}

TEST(ConfigOperations, AllowRejectionsPointAtTheItem) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow: [10.0.0.0/8, 192.168.1.0/33]
)" + kBusAndServo),
            "plant.yaml:2:23: modbus_tcp.allow[1]: \"192.168.1.0/33\": the prefix length after '/' must be 0..32 for "
            "an IPv4 network");
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow:
    - 10.0.0.0/8
    - 192.168.10.7/24
)" + kBusAndServo),
            "plant.yaml:4:7: modbus_tcp.allow[1]: \"192.168.10.7/24\" has address bits set below its /24 prefix; the "
            "network is 192.168.10.0/24 (or give /32 for the one address)");
}

TEST(ConfigOperations, AllowMustBeANonEmptyListOfStrings) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow: []
)" + kBusAndServo),
            "plant.yaml:2:10: modbus_tcp.allow: empty; remove the key to let every client connect");
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow: 10.0.0.0/8
)" + kBusAndServo),
            "plant.yaml:2:10: modbus_tcp.allow: expected a list, got `10.0.0.0/8`");
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow: [{net: 10.0.0.0/8}]
)" + kBusAndServo),
            "plant.yaml:2:11: modbus_tcp.allow[0]: expected a string, got a map");
}

TEST(ConfigOperations, AllowRefusesTheSameNetworkTwice) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  allow:
    - 10.0.0.7
    - 192.168.0.0/16
    - 10.0.0.7/32
)" + kBusAndServo),
            "plant.yaml:5:7: modbus_tcp.allow[2]: 10.0.0.7/32 is already listed as modbus_tcp.allow[0] (line 3, "
            "column 7)");
}

// ---- logging.format ----

TEST(ConfigOperations, LogFormatPlainOrJson) {
  const Config json = load_or_fail(kBusAndServo + "logging:\n  format: json\n");
  EXPECT_EQ(json.logging.format, LogFormat::Json);
  const Config plain = load_or_fail(kBusAndServo + "logging:\n  format: plain\n");
  EXPECT_EQ(plain.logging.format, LogFormat::Plain);
}

TEST(ConfigOperations, LogFormatRejectionNamesTheChoices) {
  EXPECT_EQ(error_text(kBusAndServo + "logging:\n  format: logfmt\n"),
            "plant.yaml:6:11: logging.format: expected one of plain, json, got `logfmt`");
}

TEST(ConfigOperations, DumpWritesAllowAndFormatAndLoadsBackEqual) {
  const Config config = load_or_fail(R"(modbus_tcp:
  allow: [192.168.10.0/24, "fd00::/8"]
)" + kBusAndServo + "logging:\n  format: json\n");
  const std::string dumped = dump_config(config);
  EXPECT_NE(dumped.find("  allow: [\"192.168.10.0/24\", \"fd00::/8\"]\n"), std::string::npos) << dumped;
  EXPECT_NE(dumped.find("  format: json\n"), std::string::npos) << dumped;
  const auto again = load_config_string(dumped, "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dumped;
  EXPECT_EQ(*again, config);
}

}  // namespace
}  // namespace sms::config

namespace sms::config {
namespace {

// d55d motors stop by themselves after 500 ms without an instruction: an offline one is probed at
// least every 200 ms whatever offline_probe_period_ms says, and the gap an online one can see
// (a poll period, then one worst transaction) is what --check-config reports and warns about.
TEST(D55dHeartbeatRules, OfflineMotorsAreProbedInsideTheHeartbeat) {
  BusConfig bus;
  bus.protocol = protocol::BusProtocol::D55d;
  bus.baud = 115200;
  bus.offline_probe_period = std::chrono::milliseconds{1000};
  EXPECT_EQ(effective_probe_period(bus), kD55dKeepAlive);
  bus.offline_probe_period = std::chrono::milliseconds{50};
  EXPECT_EQ(effective_probe_period(bus), std::chrono::milliseconds{50});
  bus.response_timeout = std::chrono::milliseconds{20};
  bus.retries = 2;
  bus.poll_period = std::chrono::milliseconds{20};
  // 256 bytes each way at 115200 8N1: 45 ms; (20 + 45) x 2 x 3 = 390; + the poll period.
  EXPECT_EQ(worst_transaction(bus), std::chrono::milliseconds{390});
  EXPECT_EQ(d55d_instruction_gap(bus), std::chrono::milliseconds{410});
  bus.protocol = protocol::BusProtocol::Feetech;
  bus.offline_probe_period = std::chrono::milliseconds{1000};
  EXPECT_EQ(effective_probe_period(bus), std::chrono::milliseconds{1000});
  EXPECT_EQ(d55d_instruction_gap(bus), std::nullopt);
}

}  // namespace
}  // namespace sms::config
