// docs/REGISTER_MAP.md is generated (gen-register-map); it must match what the code maps.
#include "modbus_map/register_map_doc.h"

#include <gtest/gtest.h>

#include <fstream>
#include <sstream>
#include <string>
#include "tests/modbus_map/doc_text.h"

namespace sms::modbus_map {
namespace {

using testing::read_file;

TEST(RegisterMapDoc, CommittedFileMatchesTheGenerator) {
  const std::string committed = read_file(SMS_REGISTER_MAP_PATH);
  ASSERT_FALSE(committed.empty()) << SMS_REGISTER_MAP_PATH << " is missing or empty";
  EXPECT_TRUE(committed == register_map_markdown())
      << SMS_REGISTER_MAP_PATH
      << " is out of date: run `build/bin/gen-register-map docs/REGISTER_MAP.md` and commit it";
}

TEST(RegisterMapDoc, ListsEveryTableAndProfile) {
  const std::string markdown = register_map_markdown();
  for (const char* heading : {"### Table `sts`", "### Table `sms1`", "### Table `d55d`", "### Table `smsmb`",
                              "### Profile `smsmb` over table `sts`", "### Profile `smsmb` over table `sms1`"}) {
    EXPECT_NE(markdown.find(heading), std::string::npos) << heading;
  }
  EXPECT_NE(markdown.find("| 42 | `goal_position` | RW | 2 | RAM | steps | sign-magnitude, bit 15 | -30719..30719 |"),
            std::string::npos);
  EXPECT_NE(markdown.find("| 0x86 | `fault_reset` | W | 40 `torque_enable` |"), std::string::npos);
}

}  // namespace
}  // namespace sms::modbus_map
