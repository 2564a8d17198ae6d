// The state file's values are read the same way on every architecture (docs/ARM.md: what runs
// under qemu-arm, where long has 32 bits).
#include "simulator/state_file.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>

namespace sms::simulator {
namespace {

// Loads a state file holding `line`; the error message, or "" when it loaded.
std::string load_error(const std::string& line, PersistedState* loaded = nullptr) {
  const auto path = std::filesystem::temp_directory_path() /
                    ("sms-state-file-test-" + std::to_string(::testing::UnitTest::GetInstance()->random_seed()) + "-" +
                     ::testing::UnitTest::GetInstance()->current_test_info()->name());
  std::ofstream(path) << line << "\n";
  std::string error;
  try {
    PersistedState state = load_state_file(path.string());
    if (loaded != nullptr) *loaded = std::move(state);
  } catch (const std::runtime_error& failure) {
    error = failure.what();
  }
  std::filesystem::remove(path);
  return error;
}

TEST(StateFile, ValuesUpTo32BitsLoad) {
  PersistedState state;
  ASSERT_EQ(load_error("eeprom 0 sts id=1 goal_position=0x0800 big=4294967295", &state), "");
  EXPECT_EQ(state[0].eeprom["id"], 1u);
  EXPECT_EQ(state[0].eeprom["goal_position"], 2048u);
  EXPECT_EQ(state[0].eeprom["big"], 4294967295u);
}

// "-1" wrapped to 0xFFFFFFFF and loaded where unsigned long has 32 bits (armhf); refused on amd64.
TEST(StateFile, NegativeAndTooLargeValuesAreRefusedOnEveryArchitecture) {
  for (const char* value : {"id=-1", "id=4294967296", "id=0x100000000", "id=99999999999999999999"}) {
    const std::string error = load_error(std::string("eeprom 0 sts ") + value);
    EXPECT_NE(error.find(":1: '" + std::string(value) + "' has no valid number"), std::string::npos)
        << value << ": " << error;
  }
}

}  // namespace
}  // namespace sms::simulator
