// `sms-gateway --simulate`, the README's newcomer path: live feedback, a goal position that the
// present position follows, the sync group of the six goal positions, and clients nobody here
// wrote (mbpoll, pymodbus) talking to it.
#include <gtest/gtest.h>

#include <regex>

#include "tests/support/eventually.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

class Simulate : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    gateway_ = std::make_unique<GatewayProcess>(std::vector<std::string>{"--simulate"}, 1);
  }
  static void TearDownTestSuite() { gateway_.reset(); }
  std::uint16_t port() const { return gateway_->port(); }
  static std::unique_ptr<GatewayProcess> gateway_;
};
std::unique_ptr<GatewayProcess> Simulate::gateway_;

TEST_F(Simulate, SixStsServosAreUnitsOneToSix) {
  for (int unit = 1; unit <= 6; ++unit) {
    wait_until_polled(port(), unit);
    ModbusClient client(port(), unit);
    const auto model = client.read_input(1003, 1);
    ASSERT_TRUE(model.ok()) << model.error;
    EXPECT_NE(model.values[0], 0) << "unit " << unit;
  }
  ModbusClient gateway(port(), 255);
  EXPECT_EQ(gateway.read_input(5, 2).values, (std::vector<std::uint16_t>{1, 6}));
  EXPECT_EQ(gateway.read_input(101, 1).values, std::vector<std::uint16_t>{10000});  // 1 000 000 baud
  EXPECT_EQ(ModbusClient(port(), 7).read_holding(42, 1).exception, 0x0A);
}

TEST_F(Simulate, PresentPositionFollowsAGoalPosition) {
  wait_until_polled(port(), 2);
  ModbusClient client(port(), 2);
  const auto start = client.read_input(56, 1);
  ASSERT_TRUE(start.ok()) << start.error;
  const std::uint16_t goal = start.values[0] < 2048 ? 3000 : 1000;
  ASSERT_TRUE(client.write_register(42, goal).ok());
  // The simulated servo moves at its goal speed with wire timing on: it gets there in seconds.
  EXPECT_TRUE(eventually([&] {
    const auto now = client.read_input(56, 1);
    return now.ok() && std::abs(int{now.values[0]} - int{goal}) <= 5;
  }));
}

TEST_F(Simulate, SyncGroupOfTheSixGoalPositions) {
  ModbusClient gateway(port(), 255);
  ASSERT_TRUE(gateway.write_registers(0, {2100, 2200, 2300, 2400, 2500, 2600}).ok());
  EXPECT_EQ(gateway.read_holding(0, 6).values, (std::vector<std::uint16_t>{2100, 2200, 2300, 2400, 2500, 2600}));
  EXPECT_EQ(ModbusClient(port(), 4).read_holding(42, 1).values, std::vector<std::uint16_t>{2400});
}

std::string run(const std::vector<std::string>& argv, int* exit_code) {
  ChildProcess process(argv);
  const auto status = process.wait_exit(30s);
  *exit_code = status.value_or(-1);
  return process.output();
}

TEST_F(Simulate, MbpollReadsFeedbackAndWritesAGoal) {
  wait_until_polled(port(), 1);
  const std::string p = std::to_string(port());
  int exit_code = 0;
  // mbpoll counts from 1: -r 57 is address 56 (present position); -t 3 input registers.
  const std::string feedback =
      run({"/usr/bin/mbpoll", "-m", "tcp", "-p", p, "-a", "1", "-t", "3", "-r", "57", "-c", "15", "-1", "127.0.0.1"},
          &exit_code);
  EXPECT_EQ(exit_code, 0) << feedback;
  std::smatch position;
  ASSERT_TRUE(std::regex_search(feedback, position, std::regex(R"(\[57\]:\s+(\d+))"))) << feedback;
  EXPECT_LE(std::stoi(position[1]), 4095);
  EXPECT_NE(feedback.find("[71]:"), std::string::npos) << feedback;

  // -t 4 holding registers; -r 43 is address 42 (goal position).
  const std::string write =
      run({"/usr/bin/mbpoll", "-m", "tcp", "-p", p, "-a", "1", "-t", "4", "-r", "43", "-1", "127.0.0.1", "1777"},
          &exit_code);
  EXPECT_EQ(exit_code, 0) << write;
  EXPECT_EQ(ModbusClient(port(), 1).read_holding(42, 1).values, std::vector<std::uint16_t>{1777});
}

TEST_F(Simulate, PymodbusReadsWritesAndSeesExceptions) {
  wait_until_polled(port(), 1);
  int exit_code = 0;
  const std::string output = run({"/usr/bin/python3", std::string(SMS_SOURCE_DIR) + "/tests/e2e/pymodbus_smoke.py",
                                  std::to_string(port()), "2345"},
                                 &exit_code);
  EXPECT_EQ(exit_code, 0) << output;
  EXPECT_NE(output.find("goal 2345"), std::string::npos) << output;
  EXPECT_NE(output.find("unit 99 exception 10"), std::string::npos) << output;
  EXPECT_EQ(ModbusClient(port(), 1).read_holding(42, 1).values, std::vector<std::uint16_t>{2345});
}

}  // namespace
}  // namespace sms::e2e
