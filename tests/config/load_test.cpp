// Valid configurations: defaults, every key read, dumps that load back the same.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <string>

#include "config/load.h"

// Designated initializers leave the members a test does not name at their defaults, on purpose.
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"

namespace sms::config {
namespace {

using namespace std::chrono_literals;
using modbus_map::ByteOrder;
using modbus_map::TableId;
using protocol::BusProtocol;

Config load_or_fail(std::string_view yaml) {
  auto config = load_config_string(yaml, "test.yaml");
  if (!config) {
    ADD_FAILURE() << config.error().to_string();
    return {};
  }
  return std::move(config).value();
}

constexpr std::string_view kMinimal = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
)";

TEST(ConfigLoad, MinimalConfigTakesEveryDefault) {
  const Config config = load_or_fail(kMinimal);

  EXPECT_EQ(config.modbus_tcp.listen, (HostPort{"127.0.0.1", 5020}));
  EXPECT_EQ(config.modbus_tcp.max_connections, 32u);
  EXPECT_EQ(config.modbus_tcp.idle_timeout, 60s);
  EXPECT_EQ(config.modbus_tcp.gateway_unit_id, 255);
  EXPECT_EQ(config.modbus_tcp.request_queue_depth, 64u);

  ASSERT_EQ(config.buses.size(), 1u);
  const BusConfig& bus = config.buses[0];
  EXPECT_EQ(bus.name, "arm");
  EXPECT_EQ(bus.device, "/dev/ttyUSB0");
  EXPECT_EQ(bus.protocol, BusProtocol::Feetech);
  EXPECT_EQ(bus.baud, 1000000u);
  EXPECT_EQ(bus.baud_code, 0);
  EXPECT_EQ(bus.parity, Parity::None);
  EXPECT_EQ(bus.stop_bits, 1);
  EXPECT_EQ(bus.response_timeout, 20ms);
  EXPECT_EQ(bus.retries, 2u);
  EXPECT_EQ(bus.poll_period, 20ms);
  EXPECT_EQ(bus.offline_probe_period, 1000ms);
  EXPECT_EQ(bus.reopen_period, 1000ms);
  EXPECT_TRUE(bus.poll.table_default());
  EXPECT_FALSE(bus.modbus_rtu.rs485);
  EXPECT_EQ(bus.modbus_rtu.rts, RtsMode::None);
  EXPECT_FALSE(bus.modbus_rtu.rts_delay);
  EXPECT_EQ(bus.modbus_rtu.byte_timeout, 50ms);

  ASSERT_EQ(config.servos.size(), 1u);
  const ServoConfig& servo = config.servos[0];
  EXPECT_EQ(servo.unit_id, 1);  // the servo id
  EXPECT_EQ(servo.bus, "arm");
  EXPECT_EQ(servo.bus_index, 0u);
  EXPECT_EQ(servo.servo_id, 1);
  EXPECT_EQ(servo.table, TableId::Sts);
  EXPECT_EQ(servo.profile, Profile::Native);
  EXPECT_FALSE(servo.byte_order);
  EXPECT_FALSE(servo.response_level);
  EXPECT_FALSE(servo.read_only);
  EXPECT_EQ(servo.name, "");
  EXPECT_FALSE(servo.passthrough());

  EXPECT_TRUE(config.sync_groups.empty());
  EXPECT_EQ(config.logging.level, LogLevel::Info);
  EXPECT_FALSE(config.logging.metrics_listen);
}

TEST(ConfigLoad, DefaultConstructedConfigHasTheSameDefaults) {
  const Config config = load_or_fail(kMinimal);
  Config expected;
  expected.buses.push_back(BusConfig{.name = "arm", .device = "/dev/ttyUSB0", .baud = 1000000});
  expected.servos.push_back(ServoConfig{.unit_id = 1, .bus = "arm", .servo_id = 1, .table = TableId::Sts});
  EXPECT_EQ(config, expected);
}

constexpr std::string_view kEveryKey = R"(modbus_tcp:
  listen: "[::]:1502"
  max_connections: 4
  idle_timeout_s: 0
  gateway_unit_id: 250
  request_queue_depth: 8
  allow: [192.168.10.0/24, "fd00:1::/64", 10.0.0.7]
buses:
  - name: arm
    device: /dev/serial/by-id/usb-FTDI-if00
    protocol: feetech
    baud: 500000
    parity: even
    stop_bits: 2
    response_timeout_ms: 35
    retries: 0
    poll_period_ms: 0
    offline_probe_period_ms: 2500
    reopen_period_ms: 500
    poll_fields: [present_position, moving]
  - name: base.1
    device: /dev/ttyUSB1
    protocol: d55d
    baud: 9600
    poll_range: {start: 36, count: 8}
  - name: lift
    device: /dev/ttyUSB2
    protocol: modbus-rtu
    baud: 57600
    parity: odd
    rs485: yes
    rts: down
    rts_delay_us: 250
    byte_timeout_ms: 15
servos:
  - {unit: 100, bus: arm, id: 0, table: sts, profile: smsmb, byte_order: high-first, response_level: 0,
     read_only: true, name: "Achse 1"}
  - {bus: arm, id: 7, table: sms1}
  - {unit: 3, bus: base.1, id: 7, table: d55d, response_level: 2}
  - {unit: 21, bus: lift, id: 1, table: smsmb, profile: smsmb}
  - {bus: lift, id: 247, table: passthrough}
sync_groups:
  - name: goals
    field: goal_position
    members: [7, 3]
    holding_register_start: 0x10
  - name: speed
    field: run_speed
    members: [7]
    holding_register_start: 0x12
logging:
  level: debug
  format: json
  metrics_listen: 0.0.0.0:9102
)";

Config every_key_expected() {
  Config expected;
  // Field by field: GCC 12 -O3 sees the temporary of a designated-initializer copy as maybe
  // uninitialized (-Wmaybe-uninitialized, a false positive).
  expected.modbus_tcp.listen = HostPort{"::", 1502};
  expected.modbus_tcp.max_connections = 4;
  expected.modbus_tcp.idle_timeout = 0s;
  expected.modbus_tcp.gateway_unit_id = 250;
  expected.modbus_tcp.request_queue_depth = 8;
  expected.modbus_tcp.allow = {
      IpNetwork{.family = IpNetwork::Family::V4, .address = {192, 168, 10, 0}, .prefix_length = 24},
      IpNetwork{.family = IpNetwork::Family::V6, .address = {0xfd, 0x00, 0x00, 0x01}, .prefix_length = 64},
      IpNetwork{.family = IpNetwork::Family::V4, .address = {10, 0, 0, 7}, .prefix_length = 32},
  };
  expected.buses.push_back(BusConfig{.name = "arm",
                                     .device = "/dev/serial/by-id/usb-FTDI-if00",
                                     .protocol = BusProtocol::Feetech,
                                     .baud = 500000,
                                     .baud_code = 1,
                                     .parity = Parity::Even,
                                     .stop_bits = 2,
                                     .response_timeout = 35ms,
                                     .retries = 0,
                                     .poll_period = 0ms,
                                     .offline_probe_period = 2500ms,
                                     .reopen_period = 500ms,
                                     .poll = {.fields = {"present_position", "moving"}}});
  expected.buses.push_back(BusConfig{.name = "base.1",
                                     .device = "/dev/ttyUSB1",
                                     .protocol = BusProtocol::D55d,
                                     .baud = 9600,
                                     .baud_code = 2,
                                     .poll = {.range = AddressRange{36, 8}}});
  expected.buses.push_back(
      BusConfig{.name = "lift",
                .device = "/dev/ttyUSB2",
                .protocol = BusProtocol::ModbusRtu,
                .baud = 57600,
                .baud_code = 3,
                .parity = Parity::Odd,
                .modbus_rtu = {.rs485 = true, .rts = RtsMode::Down, .rts_delay = 250us, .byte_timeout = 15ms}});
  expected.servos.push_back(ServoConfig{.unit_id = 100,
                                        .bus = "arm",
                                        .bus_index = 0,
                                        .servo_id = 0,
                                        .table = TableId::Sts,
                                        .profile = Profile::Smsmb,
                                        .byte_order = ByteOrder::HighFirst,
                                        .response_level = 0,
                                        .read_only = true,
                                        .name = "Achse 1"});
  expected.servos.push_back(
      ServoConfig{.unit_id = 7, .bus = "arm", .bus_index = 0, .servo_id = 7, .table = TableId::Sms1});
  expected.servos.push_back(ServoConfig{
      .unit_id = 3, .bus = "base.1", .bus_index = 1, .servo_id = 7, .table = TableId::D55d, .response_level = 2});
  // profile smsmb on an smsmb table is its native map
  expected.servos.push_back(ServoConfig{.unit_id = 21,
                                        .bus = "lift",
                                        .bus_index = 2,
                                        .servo_id = 1,
                                        .table = TableId::Smsmb,
                                        .profile = Profile::Native});
  expected.servos.push_back(ServoConfig{.unit_id = 247, .bus = "lift", .bus_index = 2, .servo_id = 247});
  expected.sync_groups.push_back(SyncGroupConfig{.name = "goals",
                                                 .field = "goal_position",
                                                 .members = {7, 3},
                                                 .holding_register_start = 16,
                                                 .move_time = false,
                                                 .stretch = false});
  expected.sync_groups.push_back(SyncGroupConfig{.name = "speed",
                                                 .field = "run_speed",
                                                 .members = {7},
                                                 .holding_register_start = 18,
                                                 .move_time = false,
                                                 .stretch = false});
  expected.logging =
      LoggingConfig{.level = LogLevel::Debug, .format = LogFormat::Json, .metrics_listen = HostPort{"0.0.0.0", 9102}};
  return expected;
}

TEST(ConfigLoad, EveryKeyIsRead) {
  const Config config = load_or_fail(kEveryKey);
  const Config expected = every_key_expected();
  EXPECT_EQ(config.modbus_tcp, expected.modbus_tcp);
  ASSERT_EQ(config.buses.size(), expected.buses.size());
  for (std::size_t i = 0; i < expected.buses.size(); ++i) EXPECT_EQ(config.buses[i], expected.buses[i]) << "bus " << i;
  ASSERT_EQ(config.servos.size(), expected.servos.size());
  for (std::size_t i = 0; i < expected.servos.size(); ++i) {
    EXPECT_EQ(config.servos[i], expected.servos[i]) << "servo " << i;
  }
  EXPECT_EQ(config.sync_groups, expected.sync_groups);
  EXPECT_EQ(config.logging, expected.logging);
  EXPECT_EQ(config, expected);
  EXPECT_TRUE(config.servos[4].passthrough());
}

TEST(ConfigLoad, DumpOfEveryKeyLoadsBackEqual) {
  const Config config = load_or_fail(kEveryKey);
  const std::string dumped = dump_config(config);
  const auto again = load_config_string(dumped, "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dumped;
  EXPECT_EQ(*again, config) << dumped;
}

TEST(ConfigLoad, DumpWritesTheDefaultsOut) {
  const std::string dumped = dump_config(load_or_fail(kMinimal));
  EXPECT_EQ(dumped, R"(modbus_tcp:
  listen: 127.0.0.1:5020
  max_connections: 32
  max_waiting: 16
  max_waiting_per_address: 8
  first_request_timeout_ms: 60000
  idle_timeout_s: 60
  gateway_unit_id: 255
  request_queue_depth: 64
  plain: true
buses:
  - name: arm
    device: "/dev/ttyUSB0"
    protocol: feetech
    baud: 1000000
    parity: none
    stop_bits: 1
    response_timeout_ms: 20
    retries: 2
    poll_period_ms: 20
    offline_probe_period_ms: 1000
    reopen_period_ms: 1000
    on_start: keep
    on_stop: hold
servos:
  - unit: 1
    bus: arm
    id: 1
    table: sts
    profile: native
    read_only: false
sync_groups: []
logging:
  level: info
  format: plain
)");
}

TEST(ConfigLoad, DumpQuotesNamesThatLookLikeOtherTypes) {
  Config config = load_or_fail(kMinimal);
  config.servos[0].name = "null";
  const auto again = load_config_string(dump_config(config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string();
  EXPECT_EQ(again->servos[0].name, "null");
}

TEST(ConfigLoad, UnitDefaultsToServoIdAndIdsRepeatAcrossBuses) {
  const Config config = load_or_fail(R"(buses:
  - {name: a, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: b, device: /dev/ttyUSB1, protocol: feetech, baud: 1000000}
servos:
  - {bus: a, id: 1, table: sts}
  - {unit: 101, bus: b, id: 1, table: sts}
)");
  ASSERT_EQ(config.servos.size(), 2u);
  EXPECT_EQ(config.servos[0].unit_id, 1);
  EXPECT_EQ(config.servos[1].unit_id, 101);
  EXPECT_EQ(config.servos[1].bus_index, 1u);
  EXPECT_EQ(find_unit(config, 101), &config.servos[1]);
  EXPECT_EQ(find_unit(config, 2), nullptr);
  EXPECT_EQ(find_bus(config, "b"), &config.buses[1]);
  EXPECT_EQ(find_bus(config, "c"), nullptr);
}

// docs/OPERATIONS.md: an HMI on plain Modbus gets its own read-only units of the servos a PLC
// drives; each servo is still polled and stopped once, as its first unit.
TEST(ConfigLoad, AServoShownAsAWritableAndAReadOnlyUnit) {
  const Config config = load_or_fail(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts, safe_stop: torque_off}
  - {unit: 2, bus: arm, id: 2, table: sts}
  - {unit: 101, bus: arm, id: 1, table: sts, profile: smsmb, read_only: true, safe_stop: torque_off, name: hmi-1}
  - {unit: 102, bus: arm, id: 2, table: sts, read_only: true}
  - {unit: 202, bus: arm, id: 2, table: sts, read_only: true}
)");
  ASSERT_EQ(config.servos.size(), 5u);
  EXPECT_FALSE(config.servos[0].view_of);
  EXPECT_FALSE(config.servos[1].view_of);
  EXPECT_EQ(config.servos[2].view_of, 1);
  EXPECT_EQ(config.servos[2].profile, Profile::Smsmb);
  EXPECT_EQ(config.servos[3].view_of, 2);
  EXPECT_EQ(config.servos[4].view_of, 2);
  const auto again = load_config_string(dump_config(config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(config);
  EXPECT_EQ(*again, config);
}

// docs/PLC_GUIDE.md "Safety": the ramp a hold brakes at, per bus, a servo's own first; none:
// the fastest the servo has.
TEST(ConfigLoad, AServosStopDecelerationIsItsOwnElseItsBussElseNone) {
  const Config config = load_or_fail(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, stop_deceleration: 50}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sms1, stop_deceleration: 20}
  - {unit: 11, bus: base, id: 1, table: d55d}
)");
  EXPECT_EQ(effective_stop_deceleration(config, config.servos[0]), 50);
  EXPECT_EQ(effective_stop_deceleration(config, config.servos[1]), 20);
  EXPECT_EQ(effective_stop_deceleration(config, config.servos[2]), std::nullopt);
  const auto again = load_config_string(dump_config(config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(config);
  EXPECT_EQ(*again, config);
}

TEST(ConfigLoad, TheWritableUnitOfAServoMayComeAfterItsReadOnlyOne) {
  const Config config = load_or_fail(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 101, bus: arm, id: 1, table: sts, read_only: true}
  - {unit: 1, bus: arm, id: 1, table: sts}
)");
  EXPECT_FALSE(config.servos[0].view_of);
  EXPECT_EQ(config.servos[1].view_of, 101);
  EXPECT_FALSE(config.servos[1].read_only);
}

TEST(ConfigLoad, AdjacentSyncGroupsAndGroupsAcrossBuses) {
  const Config config = load_or_fail(R"(buses:
  - {name: left, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: right, device: /dev/ttyUSB1, protocol: feetech, baud: 1000000}
servos:
  - {unit: 1, bus: left, id: 1, table: sts}
  - {unit: 2, bus: right, id: 1, table: sms1}
sync_groups:
  - {name: positions, field: goal_position, members: [1, 2], holding_register_start: 0}
  - {name: locks, field: lock, members: [1, 2], holding_register_start: 2}
)");
  ASSERT_EQ(config.sync_groups.size(), 2u);
  EXPECT_EQ(config.sync_groups[0].register_count(), 2);
  EXPECT_EQ(config.sync_groups[1].holding_register_start, 2);
}

// Timed moves (docs/PLC_GUIDE.md "Timed group moves"): the move time register after the members
// counts in the block, and both keys come back from a dump.
TEST(ConfigLoad, TimedMoveGroups) {
  const Config config = load_or_fail(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: lift, device: /dev/ttyUSB1, protocol: modbus-rtu, baud: 115200}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sms1}
  - {unit: 3, bus: arm, id: 3, table: scs}
  - {unit: 4, bus: lift, id: 1, table: smsmb}
sync_groups:
  - {name: arm, field: goal_position, members: [1, 2, 3, 4], holding_register_start: 0, move_time: true}
  - {name: again, field: goal_position, members: [1, 2], holding_register_start: 5, move_time: true, stretch: true}
)");
  ASSERT_EQ(config.sync_groups.size(), 2u);
  EXPECT_TRUE(config.sync_groups[0].move_time);
  EXPECT_FALSE(config.sync_groups[0].stretch);
  EXPECT_EQ(config.sync_groups[0].register_count(), 5);
  EXPECT_EQ(config.sync_groups[0].member_count(), 4);
  EXPECT_TRUE(config.sync_groups[1].stretch);
  const auto again = load_config_string(dump_config(config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(config);
  EXPECT_EQ(again->sync_groups, config.sync_groups);
}

TEST(ConfigLoad, YamlBooleanSpellingsAndHexNumbers) {
  const Config config = load_or_fail(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 0x1C200, rs485: On}
servos:
  - {bus: lift, id: 0x10, table: smsmb, read_only: False}
)");
  EXPECT_EQ(config.buses[0].baud, 115200u);
  EXPECT_TRUE(config.buses[0].modbus_rtu.rs485);
  EXPECT_EQ(config.servos[0].servo_id, 16);
  EXPECT_FALSE(config.servos[0].read_only);
}

TEST(ConfigLoad, BroadcastSafeServoIdZeroWithAnExplicitUnit) {
  const Config config = load_or_fail(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 5, bus: arm, id: 0, table: sts}
  - {unit: 6, bus: arm, id: 253, table: sts}
)");
  EXPECT_EQ(config.servos[0].servo_id, 0);
  EXPECT_EQ(config.servos[1].servo_id, 253);
}

TEST(ConfigLoad, EffectiveByteOrderFollowsTableUnlessOverridden) {
  ServoConfig servo{.table = TableId::Sts};
  EXPECT_EQ(effective_byte_order(servo), ByteOrder::LowFirst);
  servo.byte_order = ByteOrder::HighFirst;
  EXPECT_EQ(effective_byte_order(servo), ByteOrder::HighFirst);
  EXPECT_EQ(effective_byte_order(ServoConfig{.table = TableId::Smsmb}), ByteOrder::HighFirst);
  EXPECT_EQ(effective_byte_order(ServoConfig{.table = TableId::Scs}), ByteOrder::HighFirst);  // SCSCL SDK End = 1
  EXPECT_EQ(effective_byte_order(ServoConfig{}), ByteOrder::HighFirst);                       // passthrough
}

TEST(ConfigLoad, ReadsAFileAndNamesItInErrors) {
  const std::string path = ::testing::TempDir() + "config_load_test.yaml";
  {
    std::ofstream out(path);
    out << "buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}\nservos: [}\n";
  }
  const auto config = load_config_file(path);
  ASSERT_FALSE(config);
  EXPECT_EQ(config.error().file, path);
  EXPECT_EQ(config.error().line, 3u);
  {
    std::ofstream out(path);
    out << kMinimal;
  }
  const auto loaded = load_config_file(path);
  ASSERT_TRUE(loaded) << loaded.error().to_string();
  EXPECT_EQ(loaded->servos.size(), 1u);
  std::remove(path.c_str());
}

TEST(ConfigError, ToStringWithAndWithoutAPlace) {
  EXPECT_EQ((ConfigError{"gw.yaml", 3, 14, "bad"}).to_string(), "gw.yaml:3:14: bad");
  EXPECT_EQ((ConfigError{"gw.yaml", 0, 0, "cannot open"}).to_string(), "gw.yaml: cannot open");
}

TEST(HostPort, ParsesIpv4HostnamesAndBracketedIpv6) {
  EXPECT_EQ(*parse_host_port("0.0.0.0:502"), (HostPort{"0.0.0.0", 502}));
  EXPECT_EQ(*parse_host_port("gateway.local:5020"), (HostPort{"gateway.local", 5020}));
  EXPECT_EQ(*parse_host_port("[::1]:0"), (HostPort{"::1", 0}));
  EXPECT_EQ((HostPort{"::1", 502}).to_string(), "[::1]:502");
  EXPECT_EQ((HostPort{"127.0.0.1", 5020}).to_string(), "127.0.0.1:5020");
}

TEST(HostPort, RefusesWhatIsNotHostPort) {
  EXPECT_EQ(parse_host_port("::1:502").error(), "\"::1:502\": an IPv6 address goes in brackets, e.g. [::]:502");
  EXPECT_EQ(parse_host_port(":502").error(), "\":502\" has no host (0.0.0.0 listens on every interface)");
  EXPECT_EQ(parse_host_port("[::1]502").error(), "\"[::1]502\" needs \":PORT\" after the ']'");
  EXPECT_EQ(parse_host_port("[::1:502").error(), "\"[::1:502\" opens an IPv6 address with '[' but has no ']'");
  EXPECT_EQ(parse_host_port("host:50a").error(), "\"host:50a\" has no valid port (0..65535) after the ':'");
  EXPECT_EQ(parse_host_port("host:").error(), "\"host:\" has no valid port (0..65535) after the ':'");
}

}  // namespace
}  // namespace sms::config
