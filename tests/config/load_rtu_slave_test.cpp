// modbus_rtu_slave (config/README.md "modbus_rtu_slave") and --rtu-slave's DEVICE[:BAUD[:PARITY]].
#include <gtest/gtest.h>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;
using testing::kBusAndServo;

TEST(LoadRtuSlave, DefaultsAreTheSerialLineSpecsAndEveryUnitWithRoleOperate) {
  const auto config = load_config_string(kBusAndServo + "modbus_rtu_slave:\n  - {device: /dev/ttyUSB1}\n", "p.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  ASSERT_EQ(config->modbus_rtu_slave.size(), 1u);
  const RtuSlaveConfig& port = config->modbus_rtu_slave[0];
  EXPECT_EQ(port.device, "/dev/ttyUSB1");
  EXPECT_EQ(port.baud, 19200u);
  EXPECT_EQ(port.parity, Parity::Even);
  EXPECT_EQ(port.stop_bits, 1);
  EXPECT_EQ(port.line.frame_gap, FrameGap{});
  EXPECT_FALSE(port.line.rs485);
  EXPECT_TRUE(port.units.empty());
  EXPECT_EQ(port.role, Role::Operate);
  EXPECT_EQ(port.reopen_period, std::chrono::milliseconds{1000});
  EXPECT_EQ(port.echo, RtuEcho::Auto);
}

TEST(LoadRtuSlave, EveryKeyIsReadAndSurvivesADump) {
  const auto config = load_config_string(kBusAndServo + R"(modbus_rtu_slave:
  - {device: /dev/ttyUSB1, baud: 115200, parity: none, stop_bits: 2, frame_gap: 3.5chars, rs485: true, rts: up,
     rts_delay_us: 50, units: [1, 255], role: read, reopen_period_ms: 250, echo: on}
  - {device: /dev/ttyUSB2, baud: 1000000, frame_gap: 800us, role: engineer, echo: off}
)",
                                         "p.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  ASSERT_EQ(config->modbus_rtu_slave.size(), 2u);
  const RtuSlaveConfig& port = config->modbus_rtu_slave[0];
  EXPECT_EQ(port.baud, 115200u);
  EXPECT_EQ(port.parity, Parity::None);
  EXPECT_EQ(port.stop_bits, 2);
  EXPECT_EQ(port.line.frame_gap.kind, FrameGap::Kind::Characters);
  EXPECT_TRUE(port.line.rs485);
  EXPECT_EQ(port.line.rts, RtsMode::Up);
  EXPECT_EQ(port.line.rts_delay, std::chrono::microseconds{50});
  EXPECT_EQ(port.units, (std::vector<std::uint8_t>{1, 255}));
  EXPECT_EQ(port.role, Role::Read);
  EXPECT_EQ(port.reopen_period, std::chrono::milliseconds{250});
  EXPECT_EQ(config->modbus_rtu_slave[1].line.frame_gap.fixed, std::chrono::microseconds{800});
  EXPECT_EQ(port.echo, RtuEcho::On);
  EXPECT_EQ(config->modbus_rtu_slave[1].echo, RtuEcho::Off);
  const auto again = load_config_string(dump_config(*config), "dumped");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(*config);
  EXPECT_EQ(*again, *config);
}

TEST(LoadRtuSlave, EchoIsAutoOrABoolean) {
  const auto echo = [](const std::string& value) {
    const auto config = load_config_string(
        kBusAndServo + "modbus_rtu_slave:\n  - {device: /dev/ttyUSB1, echo: " + value + "}\n", "p.yaml");
    if (!config) throw std::runtime_error(config.error().to_string());
    return config->modbus_rtu_slave[0].echo;
  };
  EXPECT_EQ(echo("auto"), RtuEcho::Auto);
  for (const char* yes : {"on", "true", "yes"}) EXPECT_EQ(echo(yes), RtuEcho::On) << yes;
  for (const char* no : {"off", "false", "no"}) EXPECT_EQ(echo(no), RtuEcho::Off) << no;
}

TEST(LoadRtuSlave, MistakesAreNamedWithTheirPlace) {
  const auto with = [](const std::string& port) {
    return error_text(kBusAndServo + "modbus_rtu_slave:\n  - " + port + "\n");
  };
  EXPECT_EQ(with("{device: /dev/ttyUSB0}"),
            "plant.yaml:6:14: modbus_rtu_slave[0].device: /dev/ttyUSB0 is the device of bus `arm` (line 2, column 25); "
            "an upstream port needs a serial line of its own (a second adapter)");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, units: [1, 7]}"),
            "plant.yaml:6:39: modbus_rtu_slave[0].units[1]: unit 7 is not configured; configured units: 1, 255 (the "
            "last is the gateway unit)");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, units: [1, 1]}"),
            "plant.yaml:6:39: modbus_rtu_slave[0].units[1]: unit 1 is listed twice");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, units: []}"),
            "plant.yaml:6:35: modbus_rtu_slave[0].units: empty; remove the key to serve every unit");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, role: none}"),
            "plant.yaml:6:34: modbus_rtu_slave[0].role: a port with role none could ask nothing; give read, operate or "
            "engineer, or remove the port");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, baud: 5000000}"),
            "plant.yaml:6:34: modbus_rtu_slave[0].baud: 5000000 is outside 300..4000000");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, echo: sometimes}"),
            "plant.yaml:6:34: modbus_rtu_slave[0].echo: expected auto, on (the adapter hands back what the port sends) "
            "or off (it does not), got `sometimes`");
  EXPECT_EQ(with("{device: /dev/ttyUSB1, byte_timeout_ms: 5}").substr(0, 70),
            "plant.yaml:6:28: unknown key `byte_timeout_ms` in modbus_rtu_slave[0];");
  EXPECT_EQ(error_text(kBusAndServo + "modbus_rtu_slave:\n  - {device: /dev/ttyUSB1}\n  - {device: /dev/ttyUSB1}\n"),
            "plant.yaml:7:14: modbus_rtu_slave[1].device: /dev/ttyUSB1 is already modbus_rtu_slave[0]'s device (line "
            "6, column 14)");
}

TEST(RtuSlaveOption, DeviceRateAndParityFromTheRight) {
  auto port = parse_rtu_slave_option("/dev/ttyUSB1");
  ASSERT_TRUE(port) << port.error();
  EXPECT_EQ(port->device, "/dev/ttyUSB1");
  EXPECT_EQ(port->baud, 19200u);
  EXPECT_EQ(port->parity, Parity::Even);
  port = parse_rtu_slave_option("/dev/ttyUSB1:115200");
  ASSERT_TRUE(port) << port.error();
  EXPECT_EQ(port->baud, 115200u);
  EXPECT_EQ(port->parity, Parity::Even);
  port = parse_rtu_slave_option("/dev/ttyUSB1:9600:none");
  ASSERT_TRUE(port) << port.error();
  EXPECT_EQ(port->baud, 9600u);
  EXPECT_EQ(port->parity, Parity::None);
  // by-path names have colons of their own
  port = parse_rtu_slave_option("/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0:38400:odd");
  ASSERT_TRUE(port) << port.error();
  EXPECT_EQ(port->device, "/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0");
  EXPECT_EQ(port->baud, 38400u);
  EXPECT_EQ(port->parity, Parity::Odd);
  port = parse_rtu_slave_option("/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0");
  ASSERT_TRUE(port) << port.error();
  EXPECT_EQ(port->device, "/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0");

  EXPECT_FALSE(parse_rtu_slave_option(""));
  EXPECT_FALSE(parse_rtu_slave_option(":9600"));
  EXPECT_FALSE(parse_rtu_slave_option("/dev/ttyUSB1:even"));
  EXPECT_FALSE(parse_rtu_slave_option("/dev/ttyUSB1:10"));
}

TEST(RtuSlaveOption, ADeviceIsABusOrAPortOnlyOnce) {
  auto config = load_config_string(kBusAndServo, "p.yaml");
  ASSERT_TRUE(config);
  RtuSlaveConfig port;
  port.device = "/dev/ttyUSB0";
  ASSERT_TRUE(rtu_slave_conflict(*config, port));
  EXPECT_NE(rtu_slave_conflict(*config, port)->find("bus `arm`"), std::string::npos);
  port.device = "/dev/ttyUSB1";
  EXPECT_FALSE(rtu_slave_conflict(*config, port));
  config->modbus_rtu_slave.push_back(port);
  EXPECT_TRUE(rtu_slave_conflict(*config, port));
}

}  // namespace
}  // namespace sms::config
