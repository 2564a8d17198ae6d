// The console's units (docs/CONSOLE.md "Units"): every unit of the tables either parses as a plain
// scale and symbol, or is shown raw with its text; the pages get both from the one function.
#include <gtest/gtest.h>

#include <string>

#include "gateway/console/console_view.h"
#include "modbus_map/tables.h"

namespace sms::gateway::console {
namespace {

modbus_map::FieldSpec with_unit(std::string_view unit) {
  modbus_map::FieldSpec field;
  field.unit = unit;
  return field;
}

TEST(UnitScale, TheTablesUnitsAreScaleAndSymbol) {
  const auto volts = unit_scale(with_unit("0.1 V"));
  ASSERT_TRUE(volts);
  EXPECT_DOUBLE_EQ(volts->scale, 0.1);
  EXPECT_EQ(volts->symbol, "V");
  EXPECT_EQ(volts->decimals, 1);
  const auto celsius = unit_scale(with_unit("°C"));
  ASSERT_TRUE(celsius);
  EXPECT_DOUBLE_EQ(celsius->scale, 1);
  EXPECT_EQ(celsius->symbol, "°C");
  EXPECT_EQ(celsius->decimals, 0);
  const auto current = unit_scale(with_unit("6.5 mA"));
  ASSERT_TRUE(current);
  EXPECT_DOUBLE_EQ(current->scale, 6.5);
  EXPECT_EQ(current->symbol, "mA");
  const auto degrees = unit_scale(with_unit("0.087°"));
  ASSERT_TRUE(degrees);
  EXPECT_DOUBLE_EQ(degrees->scale, 0.087);
  EXPECT_EQ(degrees->symbol, "°");
  EXPECT_EQ(degrees->decimals, 3);
  EXPECT_EQ(unit_scale(with_unit("100 steps/s²"))->scale, 100);
  EXPECT_EQ(unit_scale(with_unit("steps"))->symbol, "steps");
}

TEST(UnitScale, UnitsThatAreNoPlainScaleAreShownRaw) {
  for (const char* unit : {"", "0.732 rpm or step/s", "ms / 0.1 %", "ms or 0.1 %", "deg × resolution"}) {
    EXPECT_FALSE(unit_scale(with_unit(unit))) << unit;
    EXPECT_TRUE(unit_scale_json(with_unit(unit)).is_null()) << unit;
  }
  const auto json = unit_scale_json(with_unit("0.1 %"));
  EXPECT_EQ(json.at("symbol"), "%");
  EXPECT_EQ(json.at("decimals"), 1);
}

// Every unit of every table: parsed, or one of the kinds above (a new unit is looked at here).
TEST(UnitScale, EveryTableUnitIsParsedOrKnownToBeNoScale) {
  for (const auto* table : modbus_map::all_tables()) {
    for (const auto& field : table->fields) {
      if (field.unit.empty() || unit_scale(field)) continue;
      const std::string unit(field.unit);
      EXPECT_TRUE(unit.find(" or ") != std::string::npos || unit.find("/ ") != std::string::npos ||
                  unit.find("×") != std::string::npos)
          << table->name << "." << field.name << ": " << unit;
    }
  }
}

}  // namespace
}  // namespace sms::gateway::console
