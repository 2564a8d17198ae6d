// The unit catalog (gateway/service/unit_catalog.h): one register map per servo unit, in its
// profile and byte order, the table's own map beside an smsmb profile, passthrough units known
// by id, and a unit without a map refused by name.
#include <gtest/gtest.h>

#include <stdexcept>

#include "gateway/service/unit_catalog.h"
#include "tests/gateway/service/service_plant.h"

namespace sms::gateway {
namespace {

using modbus_map::Profile;
using testing::service_plant;

TEST(UnitCatalog, EachServoUnitHasTheMapOfItsTableProfileAndByteOrder) {
  const config::Config config = service_plant();
  const UnitCatalog catalog(config);
  const CatalogUnit* native = catalog.servo(1);
  ASSERT_NE(native, nullptr);
  EXPECT_EQ(native->map.profile(), Profile::Native);
  EXPECT_EQ(native->map.description(), "table sts");
  EXPECT_EQ(&native->native_map(), &native->map);  // no second map where the first is the table's own
  EXPECT_EQ(native->servo->unit_id, 1);

  const CatalogUnit* smsmb = catalog.servo(2);
  ASSERT_NE(smsmb, nullptr);
  EXPECT_EQ(smsmb->map.profile(), Profile::Smsmb);
  EXPECT_EQ(smsmb->native_map().profile(), Profile::Native);  // the sync groups' value rules
  EXPECT_EQ(smsmb->native_map().description(), "table sts");

  ASSERT_NE(catalog.servo(3), nullptr);
  EXPECT_EQ(catalog.servo(3)->map.byte_order(), modbus_map::ByteOrder::HighFirst);
}

TEST(UnitCatalog, PassthroughGatewayAndUnknownUnitsHaveNoMap) {
  const config::Config config = service_plant();
  const UnitCatalog catalog(config);
  EXPECT_EQ(catalog.servo(10), nullptr);
  EXPECT_TRUE(catalog.passthrough(10));
  EXPECT_FALSE(catalog.passthrough(1));
  EXPECT_EQ(catalog.servo(255), nullptr);
  EXPECT_EQ(catalog.gateway_unit_id(), 255);
  EXPECT_EQ(catalog.servo(77), nullptr);
}

TEST(UnitCatalog, AUnitWithoutARegisterMapIsRefusedByName) {
  config::Config config = service_plant();
  config.servos[0].table = modbus_map::TableId::D55d;  // d55d has the native profile only
  config.servos[0].profile = config::Profile::Smsmb;
  try {
    const UnitCatalog catalog(config);
    FAIL() << "a d55d unit in the smsmb profile was taken";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("unit 1: the smsmb profile shows servos of tables sts and sms1"),
              std::string::npos)
        << error.what();
  }
}

}  // namespace
}  // namespace sms::gateway
