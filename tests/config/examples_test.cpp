// The shipped example configurations load, and say what their comments promise.
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <string>
#include <vector>

#include "config/load.h"

namespace sms::config {
namespace {

const std::filesystem::path kExamples{SMS_CONFIG_EXAMPLES_DIR};

Config load_example(const std::string& name) {
  auto config = load_config_file((kExamples / name).string());
  if (!config) {
    ADD_FAILURE() << config.error().to_string();
    return {};
  }
  return std::move(config).value();
}

TEST(ConfigExamples, EveryExampleLoadsAndSurvivesADump) {
  std::vector<std::filesystem::path> files;
  for (const auto& entry : std::filesystem::directory_iterator(kExamples)) {
    if (entry.path().extension() == ".yaml") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  ASSERT_GE(files.size(), 3u);
  for (const auto& file : files) {
    SCOPED_TRACE(file.string());
    const auto config = load_config_file(file.string());
    ASSERT_TRUE(config) << config.error().to_string();
    const auto again = load_config_string(dump_config(*config), file.string() + " (dumped)");
    ASSERT_TRUE(again) << again.error().to_string();
    EXPECT_EQ(*again, *config);
  }
}

TEST(ConfigExamples, SimulatedIsSixStsServosWithOneGoalPositionGroup) {
  const Config config = load_example("simulated.yaml");
  EXPECT_EQ(config.modbus_tcp.listen, (HostPort{"127.0.0.1", 5020}));
  ASSERT_EQ(config.buses.size(), 1u);
  EXPECT_EQ(config.buses[0].device, "/run/sms-sim/ttySIM0");
  EXPECT_EQ(config.buses[0].protocol, protocol::BusProtocol::Feetech);
  EXPECT_EQ(config.buses[0].baud, 1000000u);
  ASSERT_EQ(config.servos.size(), 6u);
  for (std::size_t i = 0; i < 6; ++i) {
    EXPECT_EQ(config.servos[i].servo_id, i + 1);
    EXPECT_EQ(config.servos[i].unit_id, i + 1);
    EXPECT_EQ(config.servos[i].table, modbus_map::TableId::Sts);
  }
  ASSERT_EQ(config.sync_groups.size(), 1u);
  EXPECT_EQ(config.sync_groups[0].field, "goal_position");
  EXPECT_EQ(config.sync_groups[0].members, (std::vector<std::uint8_t>{1, 2, 3, 4, 5, 6}));
  EXPECT_EQ(config.sync_groups[0].holding_register_start, 0);
}

TEST(ConfigExamples, MixedHasOneBusOfEachProtocol) {
  const Config config = load_example("mixed.yaml");
  ASSERT_EQ(config.buses.size(), 3u);
  EXPECT_EQ(config.buses[0].protocol, protocol::BusProtocol::Feetech);
  EXPECT_EQ(config.buses[1].protocol, protocol::BusProtocol::D55d);
  EXPECT_EQ(config.buses[2].protocol, protocol::BusProtocol::ModbusRtu);
  EXPECT_EQ(config.buses[2].poll.range, (AddressRange{0x100, 8}));
  ASSERT_NE(find_unit(config, 3), nullptr);
  EXPECT_EQ(find_unit(config, 3)->profile, Profile::Smsmb);
  EXPECT_EQ(config.logging.metrics_listen, (HostPort{"127.0.0.1", 9102}));
}

TEST(ConfigExamples, PassthroughForwardsTwoSlaves) {
  const Config config = load_example("passthrough.yaml");
  const auto passthrough = std::count_if(config.servos.begin(), config.servos.end(),
                                         [](const ServoConfig& servo) { return servo.passthrough(); });
  EXPECT_EQ(passthrough, 2);
  ASSERT_NE(find_unit(config, 30), nullptr);
  EXPECT_EQ(find_unit(config, 30)->servo_id, 31);
  EXPECT_TRUE(config.buses[0].modbus_rtu.rs485);
  EXPECT_EQ(config.buses[0].modbus_rtu.rts, RtsMode::Up);
}

}  // namespace
}  // namespace sms::config
