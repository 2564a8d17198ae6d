// The EEPROM lock rule (modbus_map/eeprom_lock.h) the console and the tools share: which tables
// have a lock and where, when a persistent change must open it, and the words both say it in.
#include "modbus_map/eeprom_lock.h"

#include <gtest/gtest.h>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

TEST(EepromLock, EveryTableWithALockFieldHasOneAndD55dHasNone) {
  ASSERT_NE(eeprom_lock(table(TableId::Sts)), nullptr);
  EXPECT_EQ(eeprom_lock(table(TableId::Sts))->addr, 55);
  EXPECT_EQ(eeprom_lock(table(TableId::Sms1))->addr, 48);
  ASSERT_NE(eeprom_lock(table(TableId::Scs)), nullptr);  // the tools had no lock for scs: its writes were lost
  EXPECT_EQ(eeprom_lock(table(TableId::Scs))->addr, 48);
  EXPECT_EQ(eeprom_lock(table(TableId::Smsmb))->addr, 0x85);
  EXPECT_EQ(eeprom_lock(table(TableId::D55d)), nullptr);  // its EEPROM writes always persist
}

TEST(EepromLock, AClosedLockIsOpenedForTheChangeAndPutBackAsItWas) {
  const FieldSpec* lock = eeprom_lock(table(TableId::Sts));
  const EepromUnlock closed{lock, 1};
  EXPECT_TRUE(closed.needed());
  EXPECT_EQ(closed.unlock_text(), "unlocking the EEPROM (lock 1 -> 0) so the change survives power-off");
  EXPECT_EQ(closed.relock_text(), "locking the EEPROM again (lock 0 -> 1)");
  EXPECT_FALSE((EepromUnlock{lock, kEepromUnlocked}.needed()));  // open already: nothing to write either way
  EXPECT_FALSE((EepromUnlock{nullptr, 1}.needed()));             // no lock at all
  // smsmb's 128 (the factory area) is put back as it was, too.
  EXPECT_EQ((EepromUnlock{eeprom_lock(table(TableId::Smsmb)), 128}.relock_text()),
            "locking the EEPROM again (lock 0 -> 128)");
}

}  // namespace
}  // namespace sms::modbus_map
