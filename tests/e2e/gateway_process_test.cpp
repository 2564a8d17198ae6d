// sms-gateway as a process: the gateway unit, sync groups, pipelining, many clients, a servo
// going offline and back, write ordering, every exception code, a bus disappearing, graceful
// stop, startup errors and the command line. Real processes and sockets only.
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/stat.h>

#include <atomic>
#include <future>
#include <mutex>

#include "tests/e2e/plant.h"
#include "tests/support/eventually.h"

// Its own namespace: the test files of e2e_tests compile in batches (unity build), where the
// helpers of one file's anonymous namespace would meet another's of the same name.
namespace sms::e2e::gateway_process_test {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using Bytes = std::vector<std::uint8_t>;

// A raw TCP connection for pipelining: many ADUs in one write.
class RawConnection {
 public:
  explicit RawConnection(std::uint16_t port) : client_(port, 1) {}
  void send(const Bytes& bytes) {
    ASSERT_EQ(::send(modbus_get_socket(client_.context()), bytes.data(), bytes.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(bytes.size()));
  }
  Bytes receive(std::size_t count) {
    Bytes out;
    const int fd = modbus_get_socket(client_.context());
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    while (out.size() < count && std::chrono::steady_clock::now() < deadline) {
      std::uint8_t buffer[1024];
      const ssize_t n = ::recv(fd, buffer, std::min(sizeof buffer, count - out.size()), MSG_DONTWAIT);
      if (n > 0) {
        out.insert(out.end(), buffer, buffer + n);
      } else if (n == 0) {
        break;
      } else {
        std::this_thread::sleep_for(1ms);
      }
    }
    return out;
  }

 private:
  ModbusClient client_;  // libmodbus only opens the socket here
};

Bytes adu(std::uint16_t tid, std::uint8_t unit, const Bytes& pdu) {
  // Sized once and filled in place (GCC 12 -O3 misreads an insert after a braced init as out of
  // bounds: -Warray-bounds).
  Bytes out(7 + pdu.size());
  out[0] = static_cast<std::uint8_t>(tid >> 8);
  out[1] = static_cast<std::uint8_t>(tid);
  out[5] = static_cast<std::uint8_t>(pdu.size() + 1);
  out[6] = unit;
  std::copy(pdu.begin(), pdu.end(), out.begin() + 7);
  return out;
}

TEST(GatewayProcess, GatewayUnitShowsVersionUptimeAndEveryBus) {
  Plant plant;
  wait_until_polled(plant.port(), 11);
  ModbusClient gateway(plant.port(), 255);
  // Every servo answers within a few poll cycles; on a loaded machine one may miss a poll at
  // first and come back at its probe.
  EXPECT_TRUE(eventually([&] {
    const auto arm = gateway.read_input(103, 1);
    const auto base = gateway.read_input(123, 1);
    return arm.ok() && base.ok() && arm.values[0] == 5 && base.values[0] == 2;
  }));
  const auto head = gateway.read_input(0, 7);
  ASSERT_TRUE(head.ok()) << head.error;
  EXPECT_EQ(head.values[0], 0);  // version 0.1.0 (CMakeLists.txt project version)
  EXPECT_EQ(head.values[1], 1);
  EXPECT_EQ(head.values[2], 0);
  EXPECT_LT((head.values[3] << 16) | head.values[4], 120);  // uptime seconds
  EXPECT_EQ(head.values[5], 2);                             // buses
  EXPECT_EQ(head.values[6], 7);                             // servos
  const auto arm = gateway.read_input(100, 10);
  ASSERT_TRUE(arm.ok()) << arm.error;
  EXPECT_EQ(arm.values[0], 1);      // up
  EXPECT_EQ(arm.values[1], 10000);  // 1 000 000 / 100
  EXPECT_EQ(arm.values[3], 5);      // servos online
  const auto base = gateway.read_input(120, 4);
  ASSERT_TRUE(base.ok()) << base.error;
  EXPECT_EQ(base.values[0], 1);
  EXPECT_EQ(base.values[1], 1152);  // 115 200 / 100
  EXPECT_EQ(base.values[3], 2);
  EXPECT_EQ(gateway.read_input(140, 1).exception, 0x02);  // there is no third bus
}

TEST(GatewayProcess, SyncGroupsWriteEveryMemberOnEachBus) {
  Plant plant;
  wait_until_polled(plant.port(), 4);
  ModbusClient gateway(plant.port(), 255);
  ASSERT_TRUE(gateway.write_registers(0, {1000, 1100, 1200}).ok());
  EXPECT_TRUE(eventually([&] { return plant.arm().field(1, "goal_position") == 1000; }));
  EXPECT_TRUE(eventually([&] { return plant.arm().field(2, "goal_position") == 1100; }));
  EXPECT_TRUE(eventually([&] { return plant.arm().field(4, "goal_position") == 1200; }));
  EXPECT_EQ(gateway.read_holding(0, 3).values, (std::vector<std::uint16_t>{1000, 1100, 1200}));

  ASSERT_TRUE(gateway.write_registers(10, {150, static_cast<std::uint16_t>(-200)}).ok());
  EXPECT_TRUE(eventually([&] { return plant.base().field(1, "run_speed") == 150; }));
  EXPECT_TRUE(eventually([&] { return plant.base().field(2, "run_speed") == -200; }));

  EXPECT_EQ(gateway.write_registers(2, {1, 2}).exception, 0x02);  // 3 is in no group
  EXPECT_EQ(gateway.write_register(20, 1).exception, 0x02);
}

TEST(GatewayProcess, PipelinedRequestsAreAnsweredInOrderWithTheirTransactionIds) {
  Plant plant;
  wait_until_polled(plant.port(), 1);
  ASSERT_TRUE(ModbusClient(plant.port(), 1).write_register(42, 2000).ok());
  RawConnection connection(plant.port());
  Bytes burst;
  for (const Bytes& request : {adu(0x0101, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}),    // goal position: 2000
                               adu(0x0102, 99, {0x03, 0x00, 0x00, 0x00, 0x01}),   // unknown unit
                               adu(0x0103, 1, {0x06, 0x00, 0x2A, 0x08, 0x34}),    // goal := 2100
                               adu(0x0104, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}),    // 2100
                               adu(0x0105, 255, {0x04, 0x00, 0x05, 0x00, 0x02}),  // 2 buses, 7 servos
                               adu(0x0106, 1, {0x07})}) {                         // unsupported
    burst.insert(burst.end(), request.begin(), request.end());
  }
  connection.send(burst);
  const Bytes expected = [] {
    Bytes all;
    for (const Bytes& answer :
         {adu(0x0101, 1, {0x03, 0x02, 0x07, 0xD0}), adu(0x0102, 99, {0x83, 0x0A}),
          adu(0x0103, 1, {0x06, 0x00, 0x2A, 0x08, 0x34}), adu(0x0104, 1, {0x03, 0x02, 0x08, 0x34}),
          adu(0x0105, 255, {0x04, 0x04, 0x00, 0x02, 0x00, 0x07}), adu(0x0106, 1, {0x87, 0x01})}) {
      all.insert(all.end(), answer.begin(), answer.end());
    }
    return all;
  }();
  EXPECT_EQ(connection.receive(expected.size()), expected);
}

TEST(GatewayProcess, FiftyConcurrentClientsAreAllServed) {
  Plant plant;
  for (const int unit : {1, 2, 3, 4, 5, 11, 12}) wait_until_polled(plant.port(), unit);
  constexpr int kClients = 50;
  constexpr int kRequests = 40;
  struct Target {
    int unit;
    int live;    // a holding register read over the bus (goal position in the unit's map)
    int cached;  // an input register served from the poll cache
  };
  const Target targets[] = {{1, 42, 56},      {2, 42, 56},  {3, 0x80, 0x101}, {4, 42, 56},
                            {5, 0x80, 0x101}, {11, 30, 36}, {12, 30, 36}};
  std::atomic<int> failures{0};
  std::mutex first_failure_mutex;
  std::string first_failure;
  std::vector<std::future<void>> clients;
  const auto started = std::chrono::steady_clock::now();
  for (int i = 0; i < kClients; ++i) {
    clients.push_back(std::async(std::launch::async, [&, i] {
      const Target& target = targets[i % 7];
      ModbusClient client(plant.port(), target.unit);
      for (int r = 0; r < kRequests; ++r) {
        // Mostly cached reads (what an HMI does), every fourth a live read over the bus.
        const auto answer = r % 4 == 3   ? client.read_holding(target.live, 1)
                            : r % 2 == 0 ? client.read_input(target.cached, 1)
                                         : client.read_input(1000, 8);
        if (!answer.ok()) {
          ++failures;
          std::lock_guard lock(first_failure_mutex);
          if (first_failure.empty()) {
            first_failure = "unit " + std::to_string(target.unit) + " request " + std::to_string(r) + ": exception " +
                            std::to_string(answer.exception) + " " + answer.error;
          }
        }
      }
    }));
  }
  for (auto& client : clients) client.get();
  EXPECT_EQ(failures, 0) << first_failure;
  EXPECT_LT(std::chrono::steady_clock::now() - started, 60s);
}

TEST(GatewayProcess, ServoGoingOfflineIs0BAndComesBackByItself) {
  Plant plant;
  wait_until_polled(plant.port(), 2);
  ModbusClient unit(plant.port(), 2);
  ASSERT_EQ(plant.arm().control("offline 2"), "ok");
  EXPECT_TRUE(eventually([&] { return unit.read_holding(42, 1).exception == 0x0B; }));
  EXPECT_TRUE(eventually([&] { return unit.read_input(1001, 1).values == std::vector<std::uint16_t>{0}; }));
  EXPECT_TRUE(eventually([&] {
    const auto age = unit.read_input(1002, 1);
    return age.ok() && age.values[0] > 200;  // the cache ages while the servo is silent
  }));
  EXPECT_TRUE(ModbusClient(plant.port(), 1).read_holding(42, 1).ok());  // the bus goes on

  ASSERT_EQ(plant.arm().control("online 2"), "ok");
  EXPECT_TRUE(eventually([&] { return unit.read_holding(42, 1).ok(); }));
  EXPECT_TRUE(eventually([&] { return unit.read_input(1001, 1).values == std::vector<std::uint16_t>{1}; }));
  const auto timeouts = unit.read_input(1006, 2);
  ASSERT_TRUE(timeouts.ok());
  EXPECT_GT((timeouts.values[0] << 16) | timeouts.values[1], 0);
}

TEST(GatewayProcess, WritesOfOneConnectionApplyInArrivalOrder) {
  Plant plant;
  wait_until_polled(plant.port(), 1);
  RawConnection connection(plant.port());
  Bytes burst;
  Bytes expected;
  // Unit 1's goal position 1000, 1001, ... 1029, interleaved with a staged write and a read.
  for (std::uint16_t i = 0; i < 30; ++i) {
    const std::uint16_t value = static_cast<std::uint16_t>(1000 + i);
    const Bytes write =
        adu(i, 1, {0x06, 0x00, 0x2A, static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)});
    burst.insert(burst.end(), write.begin(), write.end());
    expected.insert(expected.end(), write.begin(), write.end());  // FC06 echoes the request
  }
  const Bytes read = adu(99, 1, {0x03, 0x00, 0x2A, 0x00, 0x01});
  burst.insert(burst.end(), read.begin(), read.end());
  const Bytes answer = adu(99, 1, {0x03, 0x02, 0x04, 0x05});  // 1029
  expected.insert(expected.end(), answer.begin(), answer.end());
  connection.send(burst);
  EXPECT_EQ(connection.receive(expected.size()), expected);
  EXPECT_EQ(plant.arm().field(1, "goal_position"), 1029);
}

TEST(GatewayProcess, ServoRefusingAnInstructionIs04) {
  Plant plant;
  wait_until_polled(plant.port(), 1);
  ASSERT_EQ(plant.arm().control("error 1 0x10"), "ok");  // feetech bit 4: instruction refused
  ModbusClient unit(plant.port(), 1);
  EXPECT_EQ(unit.write_register(42, 1234).exception, 0x04);
  ASSERT_EQ(plant.arm().control("error 1 0"), "ok");
  EXPECT_TRUE(unit.write_register(42, 1234).ok());
}

TEST(GatewayProcess, FullBusQueueIs06) {
  Plant plant(PlantOptions{.request_queue_depth = 1, .response_timeout_ms = 500});
  wait_until_polled(plant.port(), 1);
  ASSERT_EQ(plant.arm().control("late 1 60"), "ok");
  std::atomic<int> ready{0};
  std::vector<std::future<int>> results;
  for (int i = 0; i < 8; ++i) {
    results.push_back(std::async(std::launch::async, [&] {
      ModbusClient client(plant.port(), 1);
      ++ready;
      while (ready < 8) std::this_thread::yield();
      return client.read_holding(42, 1).exception;
    }));
  }
  int busy = 0;
  int answered = 0;
  for (auto& result : results) {
    const int exception = result.get();
    busy += exception == 0x06;
    answered += exception == 0;
  }
  EXPECT_GE(busy, 1);
  EXPECT_GE(answered, 1);
  EXPECT_EQ(busy + answered, 8);
}

TEST(GatewayProcess, UnknownUnitIs0A) {
  Plant plant;
  for (const int unit : {0, 6, 13, 247}) {
    EXPECT_EQ(ModbusClient(plant.port(), unit).read_holding(42, 1).exception, 0x0A) << "unit " << unit;
  }
  // libmodbus will not address unit 254; a raw request does.
  RawConnection connection(plant.port());
  connection.send(adu(0x0254, 254, {0x03, 0x00, 0x2A, 0x00, 0x01}));
  EXPECT_EQ(connection.receive(9), adu(0x0254, 254, {0x83, 0x0A}));
}

TEST(GatewayProcess, BusWhosePortVanishedIs0A) {
  Plant plant;
  wait_until_polled(plant.port(), 11);
  plant.base().process().signal(SIGKILL);  // the pty's master closes: the bus is gone
  ModbusClient unit(plant.port(), 11);
  EXPECT_TRUE(eventually([&] { return unit.read_holding(30, 1).exception == 0x0A; }));
  EXPECT_EQ(unit.read_input(36, 1).exception, 0x0A);
  ModbusClient gateway(plant.port(), 255);
  EXPECT_EQ(gateway.read_input(120, 1).values, std::vector<std::uint16_t>{0});  // bus 1 down
  EXPECT_TRUE(ModbusClient(plant.port(), 1).read_holding(42, 1).ok());          // bus 0 unaffected
}

TEST(GatewayProcess, SigtermAnswersTheWriteInFlightThenExitsZero) {
  Plant plant(PlantOptions{.request_queue_depth = 64, .response_timeout_ms = 1000});
  wait_until_polled(plant.port(), 1);
  ASSERT_EQ(plant.arm().control("late 1 300"), "ok");
  ModbusClient unit(plant.port(), 1);
  auto write = std::async(std::launch::async, [&] { return unit.write_register(42, 3210).exception; });
  std::this_thread::sleep_for(100ms);  // the write is on the bus, waiting for the late servo
  plant.gateway().process().signal(SIGTERM);
  EXPECT_EQ(write.get(), 0);
  EXPECT_EQ(plant.arm().field(1, "goal_position"), 3210);
  EXPECT_EQ(plant.gateway().process().wait_exit(10s), std::optional<int>{0}) << plant.gateway().process().output();
}

TEST(GatewayProcess, PortInUseIsAClearStartupError) {
  Plant plant;
  const std::string listen = "127.0.0.1:" + std::to_string(plant.port());
  ChildProcess second({bin("sms-gateway"), "--simulate", "--listen", listen});
  EXPECT_EQ(second.wait_exit(15s), std::optional<int>{1});
  const std::string output = second.output();
  EXPECT_NE(output.find(listen), std::string::npos) << output;
  EXPECT_NE(output.find("--listen"), std::string::npos) << output;
}

TEST(GatewayProcess, ConfigErrorNamesFileLineAndColumn) {
  TempDir dir;
  const std::string path = dir.file("bad.yaml");
  std::ofstream(path) << "modbus_tcp:\n  listen: 127.0.0.1:5020\n  max_conections: 4\n";
  ChildProcess gateway({bin("sms-gateway"), "--config", path});
  EXPECT_EQ(gateway.wait_exit(10s), std::optional<int>{2});
  EXPECT_NE(gateway.output().find(path + ":3:3"), std::string::npos) << gateway.output();

  ChildProcess check({bin("sms-gateway"), "--check-config", path});
  EXPECT_EQ(check.wait_exit(10s), std::optional<int>{2});
  EXPECT_NE(check.output().find(path + ":3:3"), std::string::npos) << check.output();
}

TEST(GatewayProcess, CheckConfigAcceptsTheShippedExamples) {
  for (const char* example : {"simulated.yaml", "mixed.yaml", "mqtt.yaml"}) {
    ChildProcess check(
        {bin("sms-gateway"), "--check-config", std::string(SMS_SOURCE_DIR) + "/config/examples/" + example});
    EXPECT_EQ(check.wait_exit(10s), std::optional<int>{0}) << check.output();
    EXPECT_NE(check.output().find("OK"), std::string::npos) << check.output();
  }
}

// What the gateway warns about at every start, --check-config says before it: here password
// logins over plain HTTP off loopback (console.insecure_http), accepted with a warning.
TEST(GatewayProcess, CheckConfigSaysTheWarningsOfAStart) {
  TempDir dir;
  const std::string path = dir.file("insecure.yaml");
  std::ofstream(path) << "buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}\n"
                         "servos:\n  - {bus: arm, id: 1, table: sts}\n"
                         "console:\n  listen: 0.0.0.0:8080\n  insecure_http: true\n  users:\n"
                         "    - {name: shift, role: operate, password_hash: "
                         "\"$argon2id$v=19$m=65536,t=2,p=1$c29tZXNhbHQ$aGFzaA\"}\n";
  ::chmod(path.c_str(), 0600);  // password hashes: readable by the gateway's user only
  ChildProcess check({bin("sms-gateway"), "--check-config", path});
  EXPECT_EQ(check.wait_exit(10s), std::optional<int>{0}) << check.output();
  const std::string output = check.output();
  EXPECT_NE(output.find(path + ": warning: console: passwords of console.users cross the network in clear"),
            std::string::npos)
      << output;
  EXPECT_NE(output.find("OK (1 warning(s) above)"), std::string::npos) << output;
}

TEST(GatewayProcess, VersionAndMissingModeAreAnswered) {
  ChildProcess version({bin("sms-gateway"), "--version"});
  EXPECT_EQ(version.wait_exit(10s), std::optional<int>{0});
  EXPECT_NE(version.output().find("sms-gateway 0.1.0"), std::string::npos) << version.output();

  ChildProcess nothing({bin("sms-gateway")});
  EXPECT_EQ(nothing.wait_exit(10s), std::optional<int>{2});
  EXPECT_NE(nothing.output().find("--simulate"), std::string::npos) << nothing.output();
}

}  // namespace
}  // namespace sms::e2e::gateway_process_test
