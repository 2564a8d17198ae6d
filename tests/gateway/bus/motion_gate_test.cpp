// The bus engines' part of the safety rules (docs/PLC_GUIDE.md "Safety"), on every bus protocol against the
// simulator on a pty: safe stops go before everything and are never refused for a full queue,
// and motion writes that a stop overtook while they were queued never reach the wire.
#include <gtest/gtest.h>

#include <atomic>
#include <mutex>
#include <string>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "gateway/bus/motion_gate.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using modbus_map::TableId;
using protocol::Bytes;
using testing::eventually;
using testing::transact;

using testing::EngineKind;

class MotionGateTest : public ::testing::TestWithParam<EngineKind> {
 protected:
  void SetUp() override {
    const EngineKind& kind = GetParam();
    simulator_ = std::make_unique<simulator::SimulatedBus>(testing::simulated_servos({1, 2}, kind.table, kind.baud));
    simulator_->start();
    BusSettings settings = testing::bus_settings(simulator_->slave_path(), {1, 2}, kind.table, kind.baud);
    settings.response_timeout = 100ms;
    settings.queue_depth = 8;
    settings.poll = false;
    settings.discover = false;
    settings.motion_gate = gate_;
    engine_ = make_bus_engine(settings);
    engine_->start();
    ASSERT_TRUE(engine_->bus_up());
  }
  void TearDown() override {
    if (engine_) engine_->stop();
    if (simulator_) simulator_->stop();
  }

  // Servo 2 answers late: the first operation holds the bus while the others queue behind it.
  void hold_the_bus(std::atomic<int>& done) {
    simulator_->set_reply_delay(2, 60ms);
    engine_->submit(ReadOp{2, GetParam().field, 1}, Priority::ClientRead, [&](BusResult) { ++done; });
    ASSERT_TRUE(eventually([&] { return simulator_->stats().requests >= 1; }));
  }

  Bytes field_of_servo_1() {
    const std::uint16_t count = 1;
    return simulator_->read_memory(1, GetParam().field, count).value_or(Bytes{});
  }

  std::shared_ptr<MotionGate> gate_ = std::make_shared<MotionGate>();
  std::unique_ptr<simulator::SimulatedBus> simulator_;
  std::unique_ptr<BusEngine> engine_;
};

TEST_P(MotionGateTest, SafeStopsGoFirstAndAreNeverRefusedForAFullQueue) {
  std::atomic<int> done{0};
  hold_the_bus(done);
  std::mutex mutex;
  std::vector<std::string> order;
  for (int i = 0; i < 8; ++i) {
    engine_->submit(ReadOp{1, GetParam().field, 1}, Priority::ClientRead, [&](BusResult result) {
      EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
      std::lock_guard lock(mutex);
      order.push_back("read");
      ++done;
    });
  }
  BusResult full;
  engine_->submit(WriteOp{1, GetParam().field, GetParam().value(7)}, Priority::ClientWrite,
                  [&](BusResult result) { full = std::move(result); });
  EXPECT_EQ(full.status, BusStatus::QueueFull);
  engine_->submit(WriteOp{1, GetParam().field, GetParam().value(9)}, Priority::Safety, [&](BusResult result) {
    EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
    std::lock_guard lock(mutex);
    order.push_back("stop");
    ++done;
  });
  ASSERT_TRUE(eventually([&] { return done.load() == 10; }));
  std::lock_guard lock(mutex);
  ASSERT_FALSE(order.empty());
  EXPECT_EQ(order.front(), "stop");
  EXPECT_EQ(field_of_servo_1(), GetParam().value(9));
}

TEST_P(MotionGateTest, MotionWritesQueuedBeforeAStopAreDroppedNotRunAfterIt) {
  std::atomic<int> done{0};
  hold_the_bus(done);
  const MotionEpoch admitted = gate_->epoch();
  std::atomic<int> dropped{0};
  for (std::uint8_t v = 1; v <= 5; ++v) {
    WriteOp write{1, GetParam().field, GetParam().value(v)};
    write.motion_epoch = admitted;
    engine_->submit(std::move(write), Priority::ClientWrite, [&](BusResult result) {
      EXPECT_EQ(result.status, BusStatus::MotionBlocked) << result.detail;
      if (result.detail.find("motion write dropped") != std::string::npos) ++dropped;
      ++done;
    });
  }
  gate_->set_blocked(true);  // a trip or the e-stop, while the five wait behind the slow read
  engine_->submit(WriteOp{1, GetParam().field, GetParam().value(42)}, Priority::Safety, [&](BusResult result) {
    EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
    ++done;
  });
  ASSERT_TRUE(eventually([&] { return done.load() == 7; }));
  EXPECT_EQ(dropped.load(), 5);
  EXPECT_EQ(field_of_servo_1(), GetParam().value(42));  // the stop's value, nothing after it

  // Unblocked (reset): a write admitted now runs; one from before the stop still does not.
  gate_->set_blocked(false);
  WriteOp fresh{1, GetParam().field, GetParam().value(11)};
  fresh.motion_epoch = gate_->epoch();
  EXPECT_EQ(transact(*engine_, std::move(fresh)).status, BusStatus::Ok);
  WriteOp stale{1, GetParam().field, GetParam().value(12)};
  stale.motion_epoch = admitted;
  EXPECT_EQ(transact(*engine_, std::move(stale)).status, BusStatus::MotionBlocked);
  EXPECT_EQ(field_of_servo_1(), GetParam().value(11));
  // Writes that are not motion writes (epoch 0) never wait for the gate.
  gate_->set_blocked(true);
  EXPECT_EQ(transact(*engine_, WriteOp{1, GetParam().field, GetParam().value(13)}).status, BusStatus::Ok);
}

INSTANTIATE_TEST_SUITE_P(BothEngines, MotionGateTest,
                         ::testing::Values(EngineKind{"packet_sts", TableId::Sts, 1'000'000, 41},
                                           EngineKind{"rtu_smsmb", TableId::Smsmb, 115'200, 0x82}),
                         [](const ::testing::TestParamInfo<EngineKind>& info) { return info.param.name; });

}  // namespace
}  // namespace sms::gateway
