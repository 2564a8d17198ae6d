// SCS servos end to end, as an integrator runs them: `sms-sim --table scs` on a pty,
// `sms-gateway scan` telling them from STS/SMS by their byte-order flag (address 2), and
// `sms-gateway --config` with `table: scs` read and written with mbpoll — the two-byte fields
// high byte first on the bus, plain values on Modbus.
#include <gtest/gtest.h>

#include <fstream>
#include <iterator>
#include <regex>
#include <string>
#include <vector>

#include "tests/support/child_process.h"
#include "tests/support/eventually.h"
#include "tests/support/processes.h"

// Its own namespace: the test files of e2e_tests compile in batches (unity build), where the
// helpers of one file's anonymous namespace would meet another's of the same name.
namespace sms::e2e::scs_bus_process_test {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using namespace std::chrono_literals;

constexpr const char* kScsConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: head, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: head, id: 1, table: scs}
  - {unit: 2, bus: head, id: 2, table: sts}
)";

std::string run(const std::vector<std::string>& argv, int* exit_code) {
  ChildProcess process(argv);
  const auto status = process.wait_exit(60s);
  process.wait_for_line("\x01never\x01", 2s);  // let the reader collect the last lines
  *exit_code = status.value_or(-1);
  return process.output();
}

bool contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

TEST(ScsBusProcess, ScanTellsScsFromStsByTheByteOrderFlag) {
  TempDir dir;
  SimProcess sim(dir, "head", {"--servo", "1:scs:feetech:1000000", "--servo", "2:sts:feetech:1000000"});
  const std::string config = dir.file("scan.yaml");
  int exit_code = -1;
  const std::string scan = run({bin("sms-gateway"), "scan", "--device", sim.pty(), "--protocol", "feetech", "--baud",
                                "1000000", "--ids", "1-3", "--write-config", config},
                               &exit_code);
  ASSERT_EQ(exit_code, 0) << scan;
  // The SCS servo: model 1284 (SCS0009) read high byte first, flagged as table scs.
  EXPECT_TRUE(std::regex_search(scan, std::regex(R"( 1000000 +1 +1284 \(SCS0009\).*table scs)"))) << scan;
  // The STS servo: model 10760 read low byte first (the SM40BL "8.42" of the FD tool).
  EXPECT_TRUE(std::regex_search(scan, std::regex(R"( 1000000 +2 +10760 \(SM40BL\))"))) << scan;
  std::ifstream written(config);
  const std::string yaml((std::istreambuf_iterator<char>(written)), std::istreambuf_iterator<char>());
  EXPECT_TRUE(contains(yaml, "id: 1, table: scs}")) << yaml;
  EXPECT_TRUE(contains(yaml, "id: 2, table: sts}")) << yaml;
  const std::string check = run({bin("sms-gateway"), "--check-config", config}, &exit_code);
  EXPECT_EQ(exit_code, 0) << check;
}

TEST(ScsBusProcess, MbpollReadsAndWritesGoalAndPresentPosition) {
  TempDir dir;
  SimProcess sim(dir, "head", {"--servo", "1:scs:feetech:1000000", "--servo", "2:sts:feetech:1000000"});
  GatewayProcess gateway = GatewayProcess::with_config(dir, substitute(kScsConfig, "@DEVICE@", sim.pty()), 1);
  wait_until_polled(gateway.port(), 1);
  const std::string port = std::to_string(gateway.port());
  int exit_code = -1;

  // mbpoll counts from 1: -r 57 is address 56 (present position); -t 3 input registers.
  const std::string feedback =
      run({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-t", "3", "-r", "57", "-c", "1", "-1", "127.0.0.1"},
          &exit_code);
  ASSERT_EQ(exit_code, 0) << feedback;
  EXPECT_TRUE(std::regex_search(feedback, std::regex(R"(\[57\]:\s+512\b)")))
      << "power-on position 512, not the byte-swapped 2\n"
      << feedback;

  // Goal 900 (holding register 42, mbpoll -r 43): on the bus 03 84, high byte first.
  const std::string write =
      run({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-t", "4", "-r", "43", "-1", "127.0.0.1", "900"},
          &exit_code);
  ASSERT_EQ(exit_code, 0) << write;
  EXPECT_EQ(sim.control("get 1 42 2"), "03 84");
  const std::string goal =
      run({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-t", "4", "-r", "43", "-c", "1", "-1", "127.0.0.1"},
          &exit_code);
  EXPECT_TRUE(std::regex_search(goal, std::regex(R"(\[43\]:\s+900\b)"))) << goal;
  EXPECT_TRUE(eventually([&] {
    const auto present = ModbusClient(gateway.port(), 1).read_input(56, 1);
    return present.ok() && std::abs(int{present.values[0]} - 900) <= 2;
  })) << "the SCS servo did not reach its goal";

  // The lock sits at 48 on SCS (coil 48), at 55 on STS.
  ModbusClient scs(gateway.port(), 1);
  EXPECT_TRUE(scs.write_register(48, 0).ok());
  EXPECT_EQ(sim.control("get 1 48 1"), "00");
}

}  // namespace
}  // namespace sms::e2e::scs_bus_process_test
