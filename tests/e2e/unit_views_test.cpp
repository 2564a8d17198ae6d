// One servo shown as two units (docs/OPERATIONS.md "An HMI next to a PLC"): the PLC's writable
// unit and the HMI's read-only unit of the same servo, on plain Modbus TCP where there are no
// roles. The real sms-gateway on a configuration file, the real sms-sim on a pty, libmodbus
// clients: both units read the servo the PLC moves, the HMI's unit refuses writes with 0x02 and
// nothing moves, the servo is polled, counted and stopped by the watchdog once, and
// --check-config refuses a second writable unit of a servo.
#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <thread>

#include "tests/support/eventually.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

constexpr int kPlcUnit = 1;
constexpr int kHmiUnit = 101;
constexpr int kGoalPosition = 42;  // sts, holding register (RAM)

std::string config_yaml(const std::string& pty, const std::string& hmi_unit_extra) {
  return "buses:\n"
         "  - {name: line, device: \"" +
         pty +
         "\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}\n"
         "servos:\n"
         "  - {unit: 1, bus: line, id: 1, table: sts, name: axis-1}\n"
         "  - {unit: 101, bus: line, id: 1, table: sts, name: axis-1-hmi" +
         hmi_unit_extra + "}\n";
}

class UnitViews : public testing::Test {
 protected:
  void SetUp() override {
    sim_ = std::make_unique<SimProcess>(dir_, "sim", std::vector<std::string>{"--servo", "1:sts"});
  }

  TempDir dir_;
  std::unique_ptr<SimProcess> sim_;
};

TEST_F(UnitViews, CheckConfigAcceptsAReadOnlySecondUnitAndRefusesASecondWritableOne) {
  const std::string good = dir_.file("good.yaml");
  std::ofstream(good) << config_yaml(sim_->pty(), ", read_only: true");
  ChildProcess ok({bin("sms-gateway"), "--check-config", good});
  EXPECT_EQ(ok.wait_exit(10s), std::optional<int>{0}) << ok.output();
  // An accepted configuration says what each bus promises a stop.
  EXPECT_NE(ok.output().find(": bus line: worst transaction "), std::string::npos) << ok.output();
  EXPECT_NE(ok.output().find("; no watchdog"), std::string::npos) << ok.output();

  const std::string bad = dir_.file("bad.yaml");
  std::ofstream(bad) << config_yaml(sim_->pty(), "");
  ChildProcess refused({bin("sms-gateway"), "--check-config", bad});
  EXPECT_EQ(refused.wait_exit(10s), std::optional<int>{2});
  EXPECT_NE(refused.output().find("servos[1]: servo id 1 is already on bus `line` as servos[0] (unit 1, line 4"),
            std::string::npos)
      << refused.output();
  EXPECT_NE(refused.output().find("IDs on one bus must differ, or a second unit of the same servo must be "
                                  "`read_only: true`"),
            std::string::npos)
      << refused.output();
}

TEST_F(UnitViews, PlcUnitWritesHmiUnitOfTheSameServoReadsAndIsRefusedWrites) {
  GatewayProcess gateway = GatewayProcess::with_config(dir_, config_yaml(sim_->pty(), ", read_only: true"), 1);
  // One servo on the line, however many units show it.
  EXPECT_NE(gateway.process().output().find("1 of 1 servos online"), std::string::npos) << gateway.process().output();
  wait_until_polled(gateway.port(), kPlcUnit);
  wait_until_polled(gateway.port(), kHmiUnit);

  ModbusClient plc(gateway.port(), kPlcUnit);
  ModbusClient hmi(gateway.port(), kHmiUnit);
  ASSERT_TRUE(plc.write_register(kGoalPosition, 2600).ok()) << gateway.process().output();
  EXPECT_TRUE(eventually([&] { return sim_->field(1, "goal_position") == 2600; }));
  const auto seen = hmi.read_holding(kGoalPosition, 1);
  ASSERT_TRUE(seen.ok()) << seen.error;
  EXPECT_EQ(seen.values[0], 2600);
  // The poll cache behind input registers is the one servo's, for both units.
  EXPECT_TRUE(eventually([&] {
    const auto a = plc.read_input(1000, 1);
    const auto b = hmi.read_input(1000, 1);
    return a.ok() && b.ok() && a.values == b.values;
  }));

  const auto refused = hmi.write_register(kGoalPosition, 500);
  EXPECT_EQ(refused.exception, 0x02);
  std::this_thread::sleep_for(100ms);
  EXPECT_EQ(sim_->field(1, "goal_position"), 2600);
}

TEST_F(UnitViews, WatchdogStopsTheServoOnceNotOncePerUnit) {
  const std::string yaml =
      substitute(config_yaml(sim_->pty(), ", read_only: true"), "response_timeout_ms: 200}",
                 "response_timeout_ms: 200, retries: 1, watchdog: {timeout_ms: 1000, feed: any_write}}");
  GatewayProcess gateway = GatewayProcess::with_config(dir_, yaml, 1);
  wait_until_polled(gateway.port(), kPlcUnit);
  {
    ModbusClient plc(gateway.port(), kPlcUnit);
    ASSERT_TRUE(plc.write_register(kGoalPosition, 3000).ok()) << gateway.process().output();
  }  // the PLC goes away; the HMI's reads do not feed the watchdog
  ModbusClient hmi(gateway.port(), kHmiUnit);
  const auto stop = gateway.process().wait_for_line("safe stop (", 5s);
  ASSERT_TRUE(stop) << gateway.process().output();
  std::size_t mentions = 0;
  for (std::size_t at = stop->find("servo 1 "); at != std::string::npos; at = stop->find("servo 1 ", at + 1)) {
    ++mentions;
  }
  EXPECT_EQ(mentions, 1u) << *stop;
  EXPECT_TRUE(hmi.read_holding(kGoalPosition, 1).ok());
}

}  // namespace
}  // namespace sms::e2e
