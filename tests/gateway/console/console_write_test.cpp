// A value refused before anything is sent reads the same from the console's servo page and from a
// Sparkplug DCMD: both ask the one value check (RegisterMap::check_write) and word its refusal
// alike (modbus_map::to_string(MapError)); only the way in's own checks come first (the console's
// read-only units and commissioning fields, the node's metric datatypes).
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>
#include <string>

#include "config/load.h"
#include "gateway/console/console_routes.h"
#include "gateway/mqtt/sparkplug_node.h"
#include "gateway/service/unit_catalog.h"

namespace sms::gateway::console {
namespace {

namespace sp = sparkplug;

config::Config plant() {
  auto config = config::load_config_string(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sts, read_only: true}
)",
                                           "plant.yaml");
  if (!config) throw std::runtime_error(config.error().to_string());
  return *config;
}

class SameRefusal : public ::testing::Test {
 protected:
  ServoUnit servo(std::uint8_t unit_id) const {
    const CatalogUnit* unit = catalog_.servo(unit_id);
    return ServoUnit{unit_id, 0, nullptr, unit_id, unit->map, {}, std::nullopt, unit->servo->read_only, "unit"};
  }
  // The console's answer to writing `value` to `field` of unit 1: its message, or "" when taken.
  std::string console(const std::string& field, std::int64_t value, std::uint8_t unit_id = 1) const {
    const auto checked = check_field_write(servo(unit_id), field, value);
    if (checked) return "";
    EXPECT_EQ(checked.error().status, 400u);
    return nlohmann::json::parse(checked.error().body).at("error").get<std::string>();
  }
  // The Sparkplug node's refusal of a DCMD of `metric` for unit 1's field at `address`.
  std::string sparkplug(const sp::Metric& metric, std::uint16_t address) const {
    const auto& map = catalog_.servo(1)->map;
    const auto reg = device_command_value(metric, map, *map.entry_at(address));
    return reg ? "" : reg.error() + "; nothing written";  // as the node's Last Command ends it
  }

  const config::Config config_ = plant();
  const UnitCatalog catalog_{config_};
};

TEST_F(SameRefusal, AValueOutsideTheRangeIsRefusedInTheSameWordsByTheConsoleAndSparkplug) {
  const std::string expected =
      "exception 0x03 (illegal data value): value 31000 for goal_position (42) of table sts is outside "
      "-30719..30719; nothing written";
  EXPECT_EQ(console("goal_position", 31000), expected);
  EXPECT_EQ(sparkplug(sp::Metric::int16("goal_position", 31000), 42), expected);
}

TEST_F(SameRefusal, AValueNotAllowedAndAReadOnlyFieldAreRefusedInTheSameWordsToo) {
  const std::string not_allowed = console("torque_enable", 3);
  EXPECT_NE(not_allowed.find("not one of 0 1 2 128"), std::string::npos) << not_allowed;
  EXPECT_EQ(sparkplug(sp::Metric::uint16("torque_enable", 3), 40), not_allowed);
  const std::string read_only = console("present_position", 5);
  EXPECT_EQ(read_only,
            "exception 0x02 (illegal data address): present_position (56) of table sts is read-only; nothing written");
  EXPECT_EQ(sparkplug(sp::Metric::uint16("present_position", 5), 56), read_only);
}

TEST_F(SameRefusal, WhatEachWayInChecksFirstIsItsOwn) {
  EXPECT_EQ(console("goal_position", 2048), "");
  EXPECT_EQ(sparkplug(sp::Metric::int16("goal_position", 2048), 42), "");
  EXPECT_EQ(console("goal_position", 2048, 2),
            "goal_position cannot be written (the unit is read_only); nothing written");
  EXPECT_NE(console("id", 7).find("sms-gateway set-id"), std::string::npos);
  EXPECT_EQ(sparkplug(sp::Metric::boolean("goal_position", true), 42),
            "got Boolean true, the metric is Int16 (send a whole number, datatype Int16 as in the birth); nothing "
            "written");
}

}  // namespace
}  // namespace sms::gateway::console
