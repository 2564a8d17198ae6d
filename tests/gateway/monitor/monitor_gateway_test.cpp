// The bus monitor on the whole gateway (gateway.h wire_monitor()): a Modbus write through the
// router to a simulated servo on a pty shows up as the bus's write frame, with the field's name
// and value, followed by the servo's answer. A feetech and a Modbus-RTU (smsmb) bus.
#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <thread>

#include "gateway/bus/wire_monitor.h"
#include "tests/support/simulated_gateway.h"

namespace sms::gateway::testing {
namespace {

using modbus_map::FrameKind;
using modbus_map::WireDirection;

// Polls `reader` until a frame `found` accepts has come and `following` more after it, or the
// deadline passes; returns the frames from the one found on.
std::vector<MonitoredFrame> read_until(MonitorReader& reader, const std::function<bool(const MonitoredFrame&)>& found,
                                       std::size_t following, std::chrono::milliseconds timeout = 5s) {
  std::vector<MonitoredFrame> from_found;
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    for (auto& frame : reader.poll(4096).frames) {
      if (!from_found.empty() || found(frame)) from_found.push_back(std::move(frame));
    }
    if (from_found.size() > following) return from_found;
    std::this_thread::sleep_for(5ms);
  }
  return from_found;
}

bool writes(const MonitoredFrame& monitored, std::string_view instruction, std::string_view field, std::int32_t value) {
  const auto& frame = monitored.frame;
  if (frame.kind != FrameKind::Request || frame.instruction != instruction) return false;
  for (const auto& written : frame.fields) {
    if (written.name == field && written.value == value) return true;
  }
  return false;
}

constexpr const char* kTwoSts = R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: arm, device: "@DEVICE@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sts}
)";

TEST(MonitorGateway, AWriteOfGoalPositionShowsAsWriteAndTheServosAnswer) {
  SimulatedGateway gateway(sts_bus(2), kTwoSts);
  gateway.wait_until_polled(1);
  const auto monitor = gateway.gateway().wire_monitor("arm");
  ASSERT_NE(monitor, nullptr);
  EXPECT_EQ(gateway.gateway().wire_monitor(0), monitor);
  EXPECT_EQ(gateway.gateway().wire_monitor("no such bus"), nullptr);
  MonitorReader reader(monitor);

  ModbusClient client(gateway.port(), 1);
  ASSERT_TRUE(client.write_register(42, 3000).ok());  // goal_position of servo 1

  const auto frames = read_until(
      reader, [](const MonitoredFrame& f) { return writes(f, "WRITE", "goal_position", 3000); }, 1);
  ASSERT_GE(frames.size(), 2u) << "no WRITE of goal_position := 3000 on the monitor";
  EXPECT_EQ(frames[0].frame.servo, 1);
  EXPECT_EQ(frames[0].frame.direction, WireDirection::ToServos);
  EXPECT_FALSE(frames[0].frame.retry);
  const auto& answer = frames[1].frame;
  EXPECT_EQ(answer.kind, FrameKind::Answer);
  EXPECT_EQ(answer.direction, WireDirection::FromServos);
  EXPECT_EQ(answer.servo, 1);
  EXPECT_EQ(answer.instruction, "WRITE");
  EXPECT_LE(frames[0].time_ns, frames[1].time_ns);
  // The poll cycle's SYNC READ is there too, its answers with the feedback fields' values.
  const auto polled = read_until(
      reader,
      [](const MonitoredFrame& f) {
        return f.frame.kind == FrameKind::Answer && f.frame.instruction == "SYNC READ" && !f.frame.fields.empty();
      },
      0);
  ASSERT_FALSE(polled.empty());
  EXPECT_EQ(polled[0].frame.fields.front().name, "present_position");
  // Nobody fell behind.
  EXPECT_EQ(gateway.gateway().metrics().buses.at(0).monitor_dropped, 0u);
}

TEST(MonitorGateway, ADamagedAnswerAndTheRetryShowAsSuch) {
  SimulatedGateway gateway(sts_bus(2), kTwoSts);
  gateway.wait_until_polled(1);
  MonitorReader reader(gateway.gateway().wire_monitor("arm"));
  ModbusClient client(gateway.port(), 2);
  // The next answer on the bus gets one byte flipped. On a loaded machine that can be a poll's
  // answer rather than the write's: then the write is answered at once, and the test writes again
  // (another value, so its frames are told apart).
  std::vector<MonitoredFrame> frames;
  std::uint16_t value = 2500;
  bool retried_and_answered = false;
  for (int attempt = 0; attempt < 5 && !retried_and_answered; ++attempt) {
    value = static_cast<std::uint16_t>(2500 + attempt);
    frames.clear();
    gateway.bus().corrupt_next_replies(1);
    ASSERT_TRUE(client.write_register(42, value).ok());  // taken on the retry
    // Everything from the write on, until the write has been answered.
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    bool answered = false;
    while (!answered && std::chrono::steady_clock::now() < deadline) {
      for (auto& frame : reader.poll(4096).frames) {
        if (answered || (frames.empty() && !writes(frame, "WRITE", "goal_position", value))) continue;
        frames.push_back(std::move(frame));
        const auto& last = frames.back().frame;
        if (last.kind == FrameKind::Answer && last.instruction == "WRITE" && last.servo == 2) {
          answered = true;
          retried_and_answered = frames.size() > 2;
        }
      }
      std::this_thread::sleep_for(5ms);
    }
  }
  ASSERT_TRUE(retried_and_answered) << frames.size() << " frames from the write on";
  // The write, what came back damaged (a frame with a wrong checksum or LEN, or bytes that made
  // none), the same write again marked as a retry, and its answer.
  EXPECT_FALSE(frames.front().frame.retry);
  bool damaged = false;
  bool retry = false;
  for (std::size_t i = 1; i + 1 < frames.size(); ++i) {
    const auto& frame = frames[i].frame;
    if (frame.kind == FrameKind::Damaged || frame.kind == FrameKind::Noise) damaged = true;
    if (writes(frames[i], "WRITE", "goal_position", value)) {
      EXPECT_TRUE(frame.retry);
      retry = true;
    }
  }
  EXPECT_TRUE(damaged);
  EXPECT_TRUE(retry);
}

TEST(MonitorGateway, AModbusRtuBusShowsTheFunctionAndTheRegistersName) {
  simulator::BusOptions options;
  options.servos = {{1, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 115'200}};
  options.timing = false;
  options.seed = 1;
  SimulatedGateway gateway(options, R"(
modbus_tcp: {listen: "@LISTEN@"}
buses:
  - {name: lift, device: "@DEVICE@", protocol: modbus-rtu, baud: 115200, response_timeout_ms: 100,
     byte_timeout_ms: 20, poll_period_ms: 10, offline_probe_period_ms: 100}
servos:
  - {unit: 1, bus: lift, id: 1, table: smsmb}
)");
  gateway.wait_until_polled(1);
  MonitorReader reader(gateway.gateway().wire_monitor("lift"));
  ModbusClient client(gateway.port(), 1);
  ASSERT_TRUE(client.write_register(0x80, 3000).ok());  // goal_position, the servo's own register

  const auto frames = read_until(
      reader, [](const MonitoredFrame& f) { return writes(f, "write_single_register", "goal_position", 3000); }, 1);
  ASSERT_GE(frames.size(), 2u) << "no FC06 of goal_position := 3000 on the monitor";
  EXPECT_EQ(frames[0].frame.code, 0x06);
  EXPECT_EQ(frames[1].frame.kind, FrameKind::Answer);
  EXPECT_EQ(frames[1].frame.instruction, "write_single_register");
  EXPECT_EQ(frames[1].frame.servo, 1);
}

}  // namespace
}  // namespace sms::gateway::testing
