#include "modbus_map/field_unit.h"

#include <gtest/gtest.h>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

TEST(FieldUnit, LeadingNumberIsTheScale) {
  EXPECT_DOUBLE_EQ(parse_field_unit("0.1 V").scale, 0.1);
  EXPECT_EQ(parse_field_unit("0.1 V").symbol, "V");
  EXPECT_DOUBLE_EQ(parse_field_unit("0.087°").scale, 0.087);
  EXPECT_EQ(parse_field_unit("0.087°").symbol, "°");
  EXPECT_DOUBLE_EQ(parse_field_unit("10 ms").scale, 10.0);
  EXPECT_EQ(parse_field_unit("10 ms").symbol, "ms");
  EXPECT_EQ(parse_field_unit("0.1 V").decimals, 1);
  EXPECT_EQ(parse_field_unit("0.087°").decimals, 3);
  EXPECT_EQ(parse_field_unit("10 ms").decimals, 0);
  EXPECT_TRUE(parse_field_unit("0.1 V").plain);
}

// A choice or a product of units is no one scale: shown raw, with the table's whole text.
TEST(FieldUnit, AChoiceOrAProductIsNotOneScale) {
  for (const std::string_view unit : {"0.732 rpm or step/s", "ms / 0.1 %", "deg \u00d7 resolution", "10"}) {
    const FieldUnit parsed = parse_field_unit(unit);
    EXPECT_FALSE(parsed.plain) << unit;
    EXPECT_DOUBLE_EQ(parsed.scale, 1.0) << unit;
    EXPECT_EQ(parsed.symbol, unit) << unit;
  }
}

TEST(FieldUnit, NoLeadingNumberIsScaleOne) {
  for (const std::string_view unit : {"steps", "°C", "", ".5 V"}) {
    const FieldUnit parsed = parse_field_unit(unit);
    EXPECT_DOUBLE_EQ(parsed.scale, 1.0) << unit;
    EXPECT_EQ(parsed.symbol, unit) << unit;
  }
}

// Every unit string of every table parses to a positive scale, and a symbol that is a tail of it.
TEST(FieldUnit, EveryTableFieldParses) {
  for (const TableSpec* spec : all_tables()) {
    for (const FieldSpec& field : spec->fields) {
      const FieldUnit unit = field_unit(field);
      EXPECT_GT(unit.scale, 0.0) << spec->name << " " << field.name;
      EXPECT_TRUE(field.unit.ends_with(unit.symbol)) << spec->name << " " << field.name;
      if (unit.scale != 1.0) {
        EXPECT_NE(field.unit.find_first_of("0123456789"), std::string_view::npos);
      }
    }
  }
}

}  // namespace
}  // namespace sms::modbus_map
