// `sms-gateway forward` as a process: a plain Modbus TCP -> RTU gateway in front of sms-sim's
// SMSMB servos, with libmodbus TCP clients.
#include <gtest/gtest.h>

#include <signal.h>

#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/child_process.h"
#include "tests/support/eventually.h"
#include "tests/support/modbus_client.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using namespace std::chrono_literals;

// Starts `sms-gateway forward` on a free port and returns the port it logged.
std::uint16_t start_forward(ChildProcess& process) {
  const auto line = process.wait_for_line("forwarding Modbus TCP on 127.0.0.1:", 10s);
  if (!line) throw std::runtime_error("forward did not start:\n" + process.output());
  const auto at = line->find("127.0.0.1:") + 10;
  return static_cast<std::uint16_t>(std::stoi(line->substr(at)));
}

TEST(ForwardProcess, ForwardsToSmsmbServosAtARateLibmodbusCannotSetAndStopsOnSigterm) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "1-2", "--baud", "56000"}, true);
  ChildProcess forward({bin("sms-gateway"), "forward", "--device", sim.pty(), "--baud", "56000", "--listen",
                        "127.0.0.1:0", "--response-timeout-ms", "30", "--retries", "1"});
  const std::uint16_t port = start_forward(forward);

  ModbusClient client(port, 2);
  auto id = client.read_holding(0x0A, 2);
  ASSERT_TRUE(id.ok()) << id.error;
  EXPECT_EQ(id.values[0], 2);
  EXPECT_EQ(id.values[1], 4);  // baud code 4 = 56000
  ASSERT_TRUE(client.write_register(0x84, 600).ok());
  EXPECT_EQ(sim.field(2, "torque_limit"), 600);

  // The servo's own exception: SMSMB has no FC04 (docs/PROTOCOL.md §1.3).
  EXPECT_EQ(client.read_input(0x100, 1).exception, 0x01);

  // A slave nobody answers for: 0x0B after the retry.
  client.set_unit(5);
  EXPECT_EQ(client.read_holding(0x0A, 1).exception, 0x0B);

  // Unit 0: an RTU broadcast, not answered (mbusd's default): the client times out, the servos
  // have the value.
  {
    ModbusClient broadcaster(port, 0, std::chrono::milliseconds{300});
    EXPECT_FALSE(broadcaster.write_register(0x84, 700).ok());
    EXPECT_TRUE(eventually([&] { return sim.field(1, "torque_limit") == 700 && sim.field(2, "torque_limit") == 700; }));
    EXPECT_EQ(broadcaster.read_holding(0x84, 1).exception, 0x0A);
  }

  forward.signal(SIGTERM);
  EXPECT_EQ(forward.wait_exit(10s), 0) << forward.output();
}

TEST(ForwardProcess, SeveralClientsAtOnceAllGetTheirAnswers) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "1-4", "--baud", "115200"}, true);
  // A response timeout a loaded machine meets (tests/README.md "Counting on a loaded machine"):
  // the test is about every client's answers, not the timeout.
  ChildProcess forward({bin("sms-gateway"), "forward", "--device", sim.pty(), "--baud", "115200",
                        "--response-timeout-ms", "200", "--listen", "127.0.0.1:0"});
  const std::uint16_t port = start_forward(forward);
  std::vector<std::thread> clients;
  std::vector<int> failures(4, 0);
  for (int unit = 1; unit <= 4; ++unit) {
    clients.emplace_back([&, unit] {
      ModbusClient client(port, unit);
      for (int round = 0; round < 15; ++round) {
        const auto value = static_cast<std::uint16_t>(100 + unit * 10 + round);
        auto read = client.write_register(0x84, value);
        auto back = client.read_holding(0x84, 1);
        if (!read.ok() || !back.ok() || back.values[0] != value) ++failures[static_cast<std::size_t>(unit - 1)];
      }
    });
  }
  for (auto& thread : clients) thread.join();
  for (int unit = 1; unit <= 4; ++unit) {
    EXPECT_EQ(failures[static_cast<std::size_t>(unit - 1)], 0) << "unit " << unit;
    EXPECT_EQ(sim.field(unit, "torque_limit"), 100 + unit * 10 + 14);
  }
  forward.signal(SIGTERM);
  EXPECT_EQ(forward.wait_exit(10s), 0) << forward.output();
}

// mbusd's default, checked with a client configured for it (pymodbus, broadcast enabled): no
// answer to a broadcast, so the reads right after it get their own answers.
TEST(ForwardProcess, PymodbusWithBroadcastEnabledGetsNoAnswerToABroadcast) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "1-2", "--baud", "115200"}, true);
  ChildProcess forward(
      {bin("sms-gateway"), "forward", "--device", sim.pty(), "--baud", "115200", "--listen", "127.0.0.1:0"});
  const std::uint16_t port = start_forward(forward);
  EXPECT_NE(forward.output().find("unit 0 -> broadcast (not answered)"), std::string::npos) << forward.output();
  ChildProcess client(
      {"/usr/bin/python3", std::string(SMS_SOURCE_DIR) + "/tests/e2e/pymodbus_broadcast.py", std::to_string(port)});
  EXPECT_EQ(client.wait_exit(30s), 0) << client.output() << forward.output();
  EXPECT_EQ(sim.field(2, "torque_limit"), 630);
  forward.signal(SIGTERM);
  EXPECT_EQ(forward.wait_exit(10s), 0) << forward.output();
}

// --reply-on-broadcast (mbusd -b), for clients that wait for every answer (libmodbus).
TEST(ForwardProcess, ReplyOnBroadcastAnswersAWriteToUnitZeroOnceSent) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "1-2", "--baud", "115200"}, true);
  ChildProcess forward({bin("sms-gateway"), "forward", "--device", sim.pty(), "--baud", "115200", "--listen",
                        "127.0.0.1:0", "--reply-on-broadcast"});
  const std::uint16_t port = start_forward(forward);
  ModbusClient client(port, 0);
  ASSERT_TRUE(client.write_register(0x84, 640).ok()) << forward.output();
  EXPECT_TRUE(eventually([&] { return sim.field(1, "torque_limit") == 640 && sim.field(2, "torque_limit") == 640; }));
  forward.signal(SIGTERM);
  EXPECT_EQ(forward.wait_exit(10s), 0) << forward.output();
}

// One read-only rule for servo and passthrough units (access_policy.h read_only_refusal): a
// read-only passthrough unit forwards reads, refuses writes with 0x02 and functions whose
// effect the gateway cannot know with 0x01, and nothing of those reaches the slave.
TEST(PassthroughProcess, ReadOnlyPassthroughUnitForwardsReadsOnly) {
  TempDir dir;
  SimProcess sim(dir, "sim", {"--protocol", "modbus-rtu", "--ids", "7-8", "--baud", "115200"});
  auto gateway =
      GatewayProcess::with_config(dir,
                                  "buses:\n  - {name: line, device: \"" + sim.pty() +
                                      "\", protocol: modbus-rtu, baud: 115200, response_timeout_ms: 200}\n"
                                      "servos:\n"
                                      "  - {bus: line, id: 7, table: passthrough, read_only: true}\n"
                                      "  - {bus: line, id: 8, table: passthrough}\n",
                                  0);  // a line of passthrough units only is not discovered: no summary to wait for
  const long before = sim.field(7, "torque_limit");
  ModbusClient client(gateway.port(), 7);
  const auto read = client.read_holding(0x84, 1);
  ASSERT_TRUE(read.ok()) << read.error;
  EXPECT_EQ(read.values[0], before);
  EXPECT_EQ(client.write_register(0x84, 321).exception, 0x02);
  EXPECT_EQ(client.write_registers(0x84, {321}).exception, 0x02);
  const auto restart = client.raw({0x41}, 7);  // Feetech's restart: effect unknown to the gateway
  EXPECT_EQ(restart.exception, 0x01);
  const auto diagnostics = client.raw({0x08, 0x00, 0x01, 0x00, 0x00}, 7);  // 08/01 restarts a device
  EXPECT_EQ(diagnostics.exception, 0x01);
  EXPECT_EQ(sim.field(7, "torque_limit"), before);

  client.set_unit(8);  // the same line's writable unit
  ASSERT_TRUE(client.write_register(0x84, 321).ok());
  EXPECT_EQ(sim.field(8, "torque_limit"), 321);
}

}  // namespace
}  // namespace sms::e2e
