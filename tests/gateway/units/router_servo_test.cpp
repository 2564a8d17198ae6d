// Servo units and the gateway unit through the whole gateway, in-process: libmodbus client ->
// TCP -> router -> bus engine -> pty -> simulated servos. Each test states what the contract
// (docs/PLC_GUIDE.md) promises and checks it on the servo's own memory where a write is involved.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <future>
#include <mutex>
#include <thread>

#include "tests/support/loopback_client.h"
#include "tests/support/simulated_gateway.h"

namespace sms::gateway::testing {
namespace {

using Bytes = protocol::Bytes;
using test::ByteVector;
using test::LoopbackClient;

std::string config_with(const std::string& bus_options, const std::string& servos, const std::string& extra = "") {
  return "modbus_tcp: {listen: \"@LISTEN@\"" + extra +
         "}\nbuses:\n  - {name: arm, device: \"@DEVICE@\", protocol: feetech, baud: 1000000" + bus_options +
         "}\nservos:\n" + servos;
}

const std::string kTwoServos =
    "  - {unit: 1, bus: arm, id: 1, table: sts}\n  - {unit: 2, bus: arm, id: 2, table: sts}\n";
// One poll cycle after discovery, then none for an hour: bus traffic is the test's alone.
const std::string kQuietBus = ", poll_period_ms: 3600000, response_timeout_ms: 100, retries: 1";

class Router : public ::testing::Test {
 protected:
  void start(const std::string& yaml, simulator::BusOptions options = sts_bus(6),
             const std::function<void(simulator::SimulatedBus&)>& prepare = {}) {
    gateway_ = std::make_unique<SimulatedGateway>(std::move(options), yaml, prepare);
  }
  simulator::SimulatedBus& sim() { return gateway_->bus(); }
  std::uint16_t port() const { return gateway_->port(); }
  std::unique_ptr<SimulatedGateway> gateway_;
};

TEST_F(Router, HoldingRegistersAreReadLiveFromTheServo) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  ASSERT_TRUE(sim().write_memory(1, 9, Bytes{0x10, 0x00}));  // min angle limit 16, low byte first
  ModbusClient client(port(), 1);
  const auto answer = client.read_holding(9, 4);
  ASSERT_TRUE(answer.ok()) << answer.error;
  // 9 min angle limit, 10 its second byte (reads 0), 11 max angle limit (4095), 12 second byte.
  EXPECT_EQ(answer.values, (std::vector<std::uint16_t>{16, 0, 4095, 0}));
}

TEST_F(Router, InputRegistersComeFromThePollCacheWithoutBusTraffic) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  gateway_->wait_until_polled(1);
  ModbusClient client(port(), 1);
  const auto before = sim().stats().requests;
  for (int i = 0; i < 50; ++i) {
    const auto answer = client.read_input(56, 15);
    ASSERT_TRUE(answer.ok()) << answer.error;
    EXPECT_EQ(answer.values[0], *sim().read_field(1, "present_position"));
    EXPECT_EQ(answer.values[6], *sim().read_field(1, "present_voltage"));
    EXPECT_EQ(answer.values[1], 0);  // second byte of present position
  }
  EXPECT_EQ(sim().stats().requests, before);
}

TEST_F(Router, FactRegistersDescribeTheServo) {
  start(kSixStsConfig);
  gateway_->wait_until_polled(1);
  ModbusClient client(port(), 1);
  const auto facts = client.read_input(1000, 9);
  ASSERT_TRUE(facts.ok()) << facts.error;
  EXPECT_EQ(facts.values[0], 0);                            // status byte
  EXPECT_EQ(facts.values[1], 1);                            // online
  EXPECT_LT(facts.values[2], 1000);                         // cache age ms (polled every 10 ms)
  EXPECT_EQ(facts.values[3], 10760);                        // model word (SM40BL) as read at discovery
  EXPECT_GT((facts.values[4] << 16) | facts.values[5], 1);  // replies OK
  EXPECT_EQ(facts.values[6], 0);                            // timeouts, high word
  EXPECT_EQ(facts.values[7], 0);
  EXPECT_EQ(facts.values[8], 0);                          // offline reason: none, it is online
  EXPECT_EQ(client.read_input(1008, 2).exception, 0x02);  // past 1008
}

TEST_F(Router, DiscreteInputsShowTheStatusBitsAndOnline) {
  start(kSixStsConfig);
  gateway_->wait_until_polled(1);
  sim().set_error_bits(1, 0x24);  // bit 2 temperature, bit 5 overload
  ModbusClient client(port(), 1);
  ASSERT_TRUE(eventually([&] { return client.read_input(1000, 1).values == std::vector<std::uint16_t>{0x24}; }));
  const auto bits = client.read_discrete(1000, 9);
  ASSERT_TRUE(bits.ok()) << bits.error;
  EXPECT_EQ(bits.values, (std::vector<std::uint8_t>{0, 0, 1, 0, 0, 1, 0, 0, 1}));
  EXPECT_EQ(client.read_discrete(1009, 1).exception, 0x02);
}

TEST_F(Router, SignMagnitudeFieldsAreTwosComplementOnModbus) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  ModbusClient client(port(), 1);
  ASSERT_TRUE(client.write_register(46, 0xFC18).ok());           // goal speed -1000
  EXPECT_EQ(*sim().read_memory(1, 46, 2), (Bytes{0xE8, 0x83}));  // 1000 | bit 15, low byte first
  EXPECT_EQ(client.read_holding(46, 1).values, std::vector<std::uint16_t>{0xFC18});
}

TEST_F(Router, AddressAndValueExceptions) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  ModbusClient client(port(), 1);
  EXPECT_EQ(client.write_register(40, 300).exception, 0x03);  // torque enable is one byte
  EXPECT_EQ(client.write_register(56, 1).exception, 0x02);    // present position is read-only
  EXPECT_EQ(client.write_register(43, 1).exception, 0x02);    // only the second byte of goal position
  EXPECT_EQ(client.read_holding(200, 1).exception, 0x02);     // beyond the table
  EXPECT_EQ(*sim().read_field(1, "torque_enable"), 0);        // nothing was written (power-on 0)
}

TEST_F(Router, UnsupportedFunctionIs01OnEveryUnit) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  ModbusClient client(port(), 1);
  EXPECT_EQ(client.raw({0x07}, 1).exception, 0x01);
  EXPECT_EQ(client.raw({0x2B, 0x0E, 0x01, 0x00}, 1).exception, 0x01);
  EXPECT_EQ(client.raw({0x08, 0x00, 0x00, 0x12, 0x34}, 255).exception, 0x01);
}

TEST_F(Router, AQuantityOfZeroOrOverTheLimitIs03) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  ModbusClient client(port(), 1);
  EXPECT_EQ(client.raw({0x03, 0x00, 0x00, 0x00, 0x7E}, 1).exception, 0x03);        // 126 registers
  EXPECT_EQ(client.raw({0x04, 0x00, 0x00, 0x00, 0x00}, 1).exception, 0x03);        // none
  EXPECT_EQ(client.raw({0x01, 0x00, 0x00, 0x07, 0xD1}, 1).exception, 0x03);        // 2001 coils
  EXPECT_EQ(client.raw({0x10, 0x00, 0x2A, 0x00, 0x00, 0x00}, 1).exception, 0x03);  // FC16 of none
  EXPECT_EQ(client.raw({0x03, 0xFF, 0xFF, 0x00, 0x02}, 1).exception, 0x02);        // past 65535
}

TEST_F(Router, UnknownUnitAndDownBusAre0A) {
  start(
      "modbus_tcp: {listen: \"@LISTEN@\"}\n"
      "buses:\n"
      "  - {name: arm, device: \"@DEVICE@\", protocol: feetech, baud: 1000000}\n"
      "  - {name: gone, device: /nonexistent/ttyUSB9, protocol: feetech, baud: 1000000}\n"
      "servos:\n"
      "  - {unit: 1, bus: arm, id: 1, table: sts}\n"
      "  - {unit: 7, bus: gone, id: 1, table: sts}\n",
      sts_bus(1));
  ModbusClient client(port(), 99);
  EXPECT_EQ(client.read_holding(56, 1).exception, 0x0A);
  client.set_unit(7);
  EXPECT_EQ(client.read_holding(56, 1).exception, 0x0A);
  EXPECT_EQ(client.read_input(56, 1).exception, 0x0A);
  EXPECT_EQ(client.write_register(42, 100).exception, 0x0A);
  client.set_unit(255);
  const auto gone = client.read_input(120, 2);  // bus 1: state, baud / 100
  ASSERT_TRUE(gone.ok()) << gone.error;
  EXPECT_EQ(gone.values, (std::vector<std::uint16_t>{0, 10000}));
  client.set_unit(1);
  EXPECT_TRUE(client.read_holding(56, 1).ok());
}

TEST_F(Router, ServoRefusingAWriteIs04) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  sim().set_error_bits(1, 0x10);  // feetech bit 4 in a write's answer: instruction refused
  ModbusClient client(port(), 1);
  EXPECT_EQ(client.write_register(42, 1000).exception, 0x04);
  sim().set_error_bits(1, 0);
  EXPECT_TRUE(client.write_register(42, 1000).ok());
}

TEST_F(Router, RepliesCorruptThroughEveryRetryAre04) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  gateway_->wait_until_polled(1);
  sim().set_corrupt_probability(1.0);
  ModbusClient client(port(), 1);
  EXPECT_EQ(client.read_holding(56, 2).exception, 0x04);
  sim().set_corrupt_probability(0.0);
  EXPECT_TRUE(client.read_holding(56, 2).ok());
}

TEST_F(Router, OfflineServoIs0BAndComesBackByItself) {
  start(kSixStsConfig);
  gateway_->wait_until_polled(2);
  ModbusClient client(port(), 2);
  sim().set_offline(2, true);
  EXPECT_TRUE(eventually([&] { return client.read_holding(56, 1).exception == 0x0B; }));
  EXPECT_TRUE(eventually([&] { return client.read_input(1001, 1).values == std::vector<std::uint16_t>{0}; }));
  const auto stale = client.read_input(56, 1);  // the cache still serves the last values
  EXPECT_TRUE(stale.ok()) << stale.error;
  ModbusClient neighbour(port(), 1);
  EXPECT_TRUE(neighbour.read_holding(56, 1).ok());

  sim().set_offline(2, false);
  EXPECT_TRUE(eventually([&] { return client.read_holding(56, 1).ok(); }));
  EXPECT_TRUE(eventually([&] { return client.read_input(1001, 1).values == std::vector<std::uint16_t>{1}; }));
}

TEST_F(Router, FullBusQueueIs06) {
  start(config_with(", response_timeout_ms: 300, retries: 0", kTwoServos, ", request_queue_depth: 1"), sts_bus(2));
  gateway_->wait_until_polled(1);
  sim().set_reply_delay(1, 40ms);
  std::vector<std::future<int>> results;
  std::atomic<int> ready{0};
  for (int i = 0; i < 8; ++i) {
    results.push_back(std::async(std::launch::async, [&] {
      ModbusClient client(port(), 1);
      ++ready;
      while (ready < 8) std::this_thread::yield();
      return client.read_holding(42, 2).exception;
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

TEST_F(Router, StagedWriteWaitsForTheActionCoil) {
  start(kSixStsConfig);
  ModbusClient client(port(), 1);
  const auto goal_before = *sim().read_field(1, "goal_position");
  ASSERT_NE(goal_before, 1000);
  ASSERT_TRUE(client.write_register(512 + 42, 1000).ok());
  EXPECT_EQ(*sim().read_field(1, "goal_position"), goal_before);  // staged, not applied
  client.set_unit(255);
  ASSERT_TRUE(client.write_coil(0, true).ok());
  EXPECT_TRUE(eventually([&] { return *sim().read_field(1, "goal_position") == 1000; }));
  EXPECT_EQ(client.read_coils(0, 1).values, std::vector<std::uint8_t>{0});
}

TEST_F(Router, SyncGroupWriteIsOneBusFrameAndReadsBack) {
  start(config_with(
            kQuietBus,
            "  - {unit: 1, bus: arm, id: 1, table: sts}\n  - {unit: 2, bus: arm, id: 2, table: sts}\n"
            "  - {unit: 3, bus: arm, id: 3, table: sts}\n"
            "sync_groups:\n  - {name: speeds, field: goal_speed, members: [1, 2, 3], holding_register_start: 10}\n"),
        sts_bus(3));
  gateway_->wait_until_polled(3);
  ModbusClient client(port(), 255);
  const auto before = sim().stats().requests;
  ASSERT_TRUE(client.write_registers(10, {100, 0xFC18, 3000}).ok());
  EXPECT_TRUE(
      eventually([&] { return sim().stats().requests == before + 1; }));  // one SYNC WRITE frame for three servos
  EXPECT_TRUE(eventually([&] { return *sim().read_field(1, "goal_speed") == 100; }));
  EXPECT_TRUE(eventually([&] { return *sim().read_memory(2, 46, 2) == Bytes{0xE8, 0x83}; }));  // -1000 sign-magnitude
  EXPECT_TRUE(eventually([&] { return *sim().read_field(3, "goal_speed") == 3000; }));
  EXPECT_EQ(client.read_holding(10, 3).values, (std::vector<std::uint16_t>{100, 0xFC18, 3000}));
  EXPECT_EQ(client.write_registers(12, {1, 2}).exception, 0x02);  // 13 is no group register
  EXPECT_EQ(client.write_register(11, 0x8000).exception, 0x03);   // -32768: beyond a 15-bit magnitude
}

TEST_F(Router, GatewayUnitInputRegisters) {
  start(kSixStsConfig);
  gateway_->wait_until_polled(6);
  ModbusClient client(port(), 255);
  const auto head = client.read_input(0, 7);
  ASSERT_TRUE(head.ok()) << head.error;
  EXPECT_EQ(head.values[0], SMS_GATEWAY_VERSION_MAJOR);
  EXPECT_EQ(head.values[1], SMS_GATEWAY_VERSION_MINOR);
  EXPECT_EQ(head.values[2], SMS_GATEWAY_VERSION_PATCH);
  EXPECT_LT((head.values[3] << 16) | head.values[4], 60);  // uptime seconds
  EXPECT_EQ(head.values[5], 1);                            // buses
  EXPECT_EQ(head.values[6], 6);                            // servos
  const auto bus = client.read_input(100, 10);
  ASSERT_TRUE(bus.ok()) << bus.error;
  EXPECT_EQ(bus.values[0], 1);                           // up
  EXPECT_EQ(bus.values[1], 10000);                       // 1 000 000 / 100
  EXPECT_EQ(bus.values[3], 6);                           // online
  EXPECT_GT((bus.values[4] << 16) | bus.values[5], 6);   // frames OK
  EXPECT_EQ(client.read_input(119, 2).exception, 0x02);  // only one bus
}

TEST_F(Router, SmsmbProfileShowsFeetechModbusRegisters) {
  start(kSixStsConfig);
  gateway_->wait_until_polled(3);
  ModbusClient client(port(), 3);
  const auto feedback = client.read_input(0x101, 1);
  ASSERT_TRUE(feedback.ok()) << feedback.error;
  EXPECT_EQ(feedback.values[0], *sim().read_field(3, "present_position"));
  ASSERT_TRUE(client.write_register(0x80, 1500).ok());  // goal position
  EXPECT_EQ(*sim().read_field(3, "goal_position"), 1500);
  EXPECT_EQ(client.read_holding(0x80, 1).values, std::vector<std::uint16_t>{1500});
  EXPECT_EQ(client.read_holding(0x40, 1).values, std::vector<std::uint16_t>{0});  // no register: reads 0
  EXPECT_EQ(client.read_holding(0x1F0, 1).exception, 0x02);                       // beyond the SMSMB map
}

TEST_F(Router, WriteToAServoThatDoesNotAnswerWritesIsAnsweredOnceSent) {
  start(config_with(kQuietBus, "  - {unit: 1, bus: arm, id: 1, table: sts, response_level: 0}\n"), sts_bus(1));
  ASSERT_TRUE(sim().write_memory(1, 8, Bytes{0x00}));  // the servo answers only READ and PING
  ModbusClient client(port(), 1);
  ASSERT_TRUE(client.write_register(42, 1234).ok());
  EXPECT_TRUE(eventually([&] { return *sim().read_field(1, "goal_position") == 1234; }));
}

TEST_F(Router, ResponseLevelReadAtDiscoveryDecidesWhetherAWriteWaitsForAnAnswer) {
  // No response_level in the configuration: the gateway reads it from the servo.
  start(config_with(", poll_period_ms: 3600000, response_timeout_ms: 300, retries: 0", kTwoServos), sts_bus(2),
        [](simulator::SimulatedBus& bus) { ASSERT_TRUE(bus.write_memory(1, 8, Bytes{0x00})); });
  gateway_->wait_until_polled(1);
  ModbusClient client(port(), 1);
  const auto started = std::chrono::steady_clock::now();
  ASSERT_TRUE(client.write_register(42, 1500).ok());
  // Not waiting for an answer that never comes: well under the 300 ms response timeout.
  EXPECT_LT(std::chrono::steady_clock::now() - started, 250ms);
  EXPECT_TRUE(eventually([&] { return *sim().read_field(1, "goal_position") == 1500; }));
  ModbusClient answering(port(), 2);  // level 1: its write is acknowledged
  EXPECT_TRUE(answering.write_register(42, 1600).ok());
  EXPECT_EQ(*sim().read_field(2, "goal_position"), 1600);
}

TEST_F(Router, PipelinedWritesOfOneConnectionApplyInOrder) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  LoopbackClient client(port());
  ByteVector burst;
  for (std::uint16_t i = 0; i < 20; ++i) {
    const std::uint16_t value = static_cast<std::uint16_t>(100 + i);
    burst.insert(burst.end(), {0x00, static_cast<std::uint8_t>(i), 0x00, 0x00, 0x00, 0x06, 0x01, 0x06, 0x00, 0x2A,
                               static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)});
  }
  burst.insert(burst.end(), {0x00, 0x63, 0x00, 0x00, 0x00, 0x06, 0x01, 0x03, 0x00, 0x2A, 0x00, 0x01});
  client.send(burst);
  for (std::uint16_t i = 0; i < 20; ++i) {
    EXPECT_EQ(client.receive(12), (ByteVector{0x00, static_cast<std::uint8_t>(i), 0x00, 0x00, 0x00, 0x06, 0x01, 0x06,
                                              0x00, 0x2A, 0x00, static_cast<std::uint8_t>(100 + i)}));
  }
  EXPECT_EQ(client.receive(11), (ByteVector{0x00, 0x63, 0x00, 0x00, 0x00, 0x05, 0x01, 0x03, 0x02, 0x00, 0x77}));
  EXPECT_EQ(*sim().read_field(1, "goal_position"), 119);
}

// Per-connection fairness (docs/DECISIONS.md "Gateway"): a session hands the router one request
// at a time, so a connection has at most one operation in a bus queue. One client pipelining 20
// slow writes cannot make another connection's request wait for them: on the wire it comes
// second or third, not twenty-first.
TEST_F(Router, APipeliningClientCannotMakeAnotherConnectionWaitForItsBurst) {
  start(config_with(kQuietBus, kTwoServos), sts_bus(2));
  gateway_->wait_until_polled(1);
  gateway_->wait_until_polled(2);
  std::mutex mutex;
  std::vector<std::uint8_t> ids;  // request frames on the wire, by servo
  sim().set_frame_observer([&](const simulator::ReceivedFrame& frame) {
    std::lock_guard lock(mutex);
    ids.push_back(frame.id);
  });
  sim().set_reply_delay(1, 20ms);  // each of the burst's writes holds the bus 20 ms
  LoopbackClient chatty(port());
  ByteVector burst;
  for (std::uint8_t i = 0; i < 20; ++i) {
    burst.insert(burst.end(),
                 {0x00, i, 0x00, 0x00, 0x00, 0x06, 0x01, 0x06, 0x00, 0x2A, 0x00, static_cast<std::uint8_t>(100 + i)});
  }
  chatty.send(burst);
  ASSERT_TRUE(eventually([&] {
    std::lock_guard lock(mutex);
    return !ids.empty();
  }));  // the burst's first write is on the wire
  LoopbackClient other(port());
  other.send({0x00, 0x77, 0x00, 0x00, 0x00, 0x06, 0x02, 0x03, 0x00, 0x2A, 0x00, 0x01});  // unit 2: goal
  EXPECT_EQ(other.receive(11).size(), 11u);
  for (int i = 0; i < 20; ++i) EXPECT_EQ(chatty.receive(12).size(), 12u);
  sim().set_frame_observer({});
  std::lock_guard lock(mutex);
  const auto position = std::find(ids.begin(), ids.end(), 2) - ids.begin();
  EXPECT_LE(position, 2) << "the other connection's read went on the wire after " << position
                         << " of the burst's writes";
  EXPECT_EQ(std::count(ids.begin(), ids.end(), 1), 20);
}

TEST_F(Router, WriteOfAClientThatLeftIsStillApplied) {
  start(config_with(", poll_period_ms: 3600000, response_timeout_ms: 300, retries: 0", kTwoServos), sts_bus(2));
  gateway_->wait_until_polled(1);
  sim().set_reply_delay(1, 100ms);
  {
    LoopbackClient client(port());
    client.send({0x00, 0x01, 0x00, 0x00, 0x00, 0x06, 0x01, 0x06, 0x00, 0x2A, 0x03, 0x09});  // goal 777
  }  // gone before the servo answers
  EXPECT_TRUE(eventually([&] { return *sim().read_field(1, "goal_position") == 777; }));
  sim().set_reply_delay(1, 0ms);
  ModbusClient next(port(), 1);
  EXPECT_EQ(next.read_holding(42, 1).values, std::vector<std::uint16_t>{777});
}

}  // namespace
}  // namespace sms::gateway::testing
