// The integrator tools as an integrator runs them: `sms-gateway scan | set-id | set-baud |
// calibrate-middle | dump` processes against sms-sim processes on ptys.
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "tests/support/child_process.h"
#include "tests/support/eventually.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using namespace std::chrono_literals;

Finished run_gateway(std::vector<std::string> args, std::chrono::milliseconds timeout = 60s) {
  std::vector<std::string> argv{bin("sms-gateway")};
  argv.insert(argv.end(), args.begin(), args.end());
  return run_to_end(argv, timeout);
}

bool contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

TEST(ToolsCli, ScanFindsServosAtTwoRatesAndWritesAConfigThatChecks) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--servo", "1:sts:feetech:1000000", "--servo", "5:sts:feetech:500000"}, true);
  const std::string config = dir.file("scan.yaml");
  const Finished scan = run_gateway({"scan", "--device", sim.pty(), "--protocol", "feetech", "--baud", "1000000,500000",
                                     "--ids", "1-8", "--write-config", config});
  ASSERT_EQ(scan.status, 0) << scan.output;
  EXPECT_TRUE(contains(scan.output, " 1000000    1 ")) << scan.output;
  EXPECT_TRUE(contains(scan.output, "  500000    5 ")) << scan.output;
  ASSERT_TRUE(std::filesystem::exists(config));
  const Finished check = run_gateway({"--check-config", config});
  EXPECT_EQ(check.status, 0) << check.output;
}

TEST(ToolsCli, ScanReportsTwoServosOnOneId) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "2,3", "--duplicate", "3"}, true);
  const Finished scan =
      run_gateway({"scan", "--device", sim.pty(), "--protocol", "modbus-rtu", "--baud", "115200", "--ids", "1-4"});
  ASSERT_EQ(scan.status, 0) << scan.output;
  EXPECT_TRUE(contains(scan.output, "two or more servos answer on this ID")) << scan.output;
  EXPECT_TRUE(contains(scan.output, "1 ID conflict(s)")) << scan.output;
}

TEST(ToolsCli, SetIdAndSetBaudSurviveASimulatorRestart) {
  TempDir dir;
  const std::string state = dir.file("eeprom.state");
  const std::vector<std::string> bus{"--servo", "1:smsmb:modbus-rtu:115200", "--state-file", state};
  {
    SimProcess sim(dir, "first", bus, true);
    const Finished set_id = run_gateway({"set-id", "--device", sim.pty(), "--protocol", "modbus-rtu", "--baud",
                                         "115200", "--id", "1", "--new-id", "9"});
    ASSERT_EQ(set_id.status, 0) << set_id.output;
    EXPECT_TRUE(contains(set_id.output, "now answers on ID 9")) << set_id.output;
    const Finished set_baud = run_gateway({"set-baud", "--device", sim.pty(), "--protocol", "modbus-rtu", "--baud",
                                           "115200", "--id", "9", "--new-baud", "14400"});
    ASSERT_EQ(set_baud.status, 0) << set_baud.output;
  }
  SimProcess again(dir, "second", bus, true);
  const Finished dump =
      run_gateway({"dump", "--device", again.pty(), "--protocol", "modbus-rtu", "--baud", "14400", "--id", "9"});
  ASSERT_EQ(dump.status, 0) << dump.output;
  EXPECT_TRUE(contains(dump.output, "id ")) << dump.output;
  // The dump's id and baud_rate lines: register 0x0A holds 9, 0x0B holds code 7 (14400).
  std::istringstream lines(dump.output);
  std::string line;
  bool id_seen = false;
  bool baud_seen = false;
  while (std::getline(lines, line)) {
    if (contains(line, " id ")) id_seen = contains(line, "  9  ");
    if (contains(line, " baud_rate ")) baud_seen = contains(line, "  7  ");
  }
  EXPECT_TRUE(id_seen) << dump.output;
  EXPECT_TRUE(baud_seen) << dump.output;
}

TEST(ToolsCli, RefusesDangerousMistakesWithAReason) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--ids", "1-2"}, true);
  const std::vector<std::string> line{"--device", sim.pty(), "--protocol", "feetech", "--baud", "1000000"};
  auto with = [&](std::vector<std::string> head, std::vector<std::string> tail) {
    head.insert(head.end(), line.begin(), line.end());
    head.insert(head.end(), tail.begin(), tail.end());
    return head;
  };
  const Finished taken = run_gateway(with({"set-id"}, {"--id", "1", "--new-id", "2"}));
  EXPECT_EQ(taken.status, 1);
  EXPECT_TRUE(contains(taken.output, "ID 2 is already taken")) << taken.output;
  const Finished bad_rate = run_gateway(with({"set-baud"}, {"--id", "1", "--new-baud", "123456"}));
  EXPECT_EQ(bad_rate.status, 1);
  EXPECT_TRUE(contains(bad_rate.output, "123456")) << bad_rate.output;
  const Finished broadcast = run_gateway(with({"set-id"}, {"--id", "254", "--new-id", "7"}));
  EXPECT_EQ(broadcast.status, 1);
  EXPECT_TRUE(contains(broadcast.output, "--force")) << broadcast.output;
  EXPECT_EQ(sim.field(1, "id"), 1);
  EXPECT_EQ(sim.field(2, "id"), 2);
  const Finished bad_ids = run_gateway({"scan", "--device", sim.pty(), "--protocol", "feetech", "--ids", "9-3"});
  EXPECT_EQ(bad_ids.status, 2);
  EXPECT_TRUE(contains(bad_ids.output, "--ids")) << bad_ids.output;
  // 2^32 + 1 is not ID 1 (it was, truncated, where unsigned long has 64 bits).
  const Finished huge_id = run_gateway({"scan", "--device", sim.pty(), "--protocol", "feetech", "--ids", "4294967297"});
  EXPECT_EQ(huge_id.status, 2);
  EXPECT_TRUE(contains(huge_id.output, "IDs are 0-253")) << huge_id.output;
}

TEST(ToolsCli, CalibrateMiddleMakesThePresentPositionTheCentre) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--ids", "3"}, true);
  sim.control("set 3 42 28 0A");  // goal position 2600
  ASSERT_TRUE(eventually([&] { return sim.field(3, "present_position") == 2600; }));
  const Finished calibrate = run_gateway(
      {"calibrate-middle", "--device", sim.pty(), "--protocol", "feetech", "--baud", "1000000", "--id", "3"});
  ASSERT_EQ(calibrate.status, 0) << calibrate.output;
  EXPECT_EQ(sim.field(3, "present_position"), 2048);
}

}  // namespace
}  // namespace sms::e2e
