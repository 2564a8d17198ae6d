// An RS-485 adapter without echo suppression hands the host its own frame back before the
// servo's answer. Here a relay between the engine's pty and the simulator's pty plays that
// adapter (tests/support/echoing_adapter.h): everything the engine sends goes to the (real,
// simulated) servos and straight back. The tools through the same adapter: tests/gateway/tools.
#include <gtest/gtest.h>

#include <memory>

#include "tests/support/bus_test_support.h"
#include "tests/support/echoing_adapter.h"

namespace sms::gateway {
namespace {

using namespace testing;
using test::EchoingAdapter;
using namespace std::chrono_literals;
using protocol::Bytes;

class EchoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    simulator_.start();
    adapter_ = std::make_unique<EchoingAdapter>(simulator_.slave_path(), 1'000'000);
    BusSettings settings = bus_settings(adapter_->host_path(), {1, 2});
    settings.poll = false;
    settings.discover = false;
    engine_ = make_bus_engine(settings);
    engine_->start();
  }
  void TearDown() override {
    if (engine_) engine_->stop();  // SetUp may have thrown before making it
    adapter_.reset();
    simulator_.stop();
  }
  simulator::SimulatedBus simulator_{simulated_servos({1, 2})};
  std::unique_ptr<EchoingAdapter> adapter_;
  std::unique_ptr<BusEngine> engine_;
};

TEST_F(EchoTest, EchoedPingIsNotTakenForTheServosAnswer) {
  // The echo FF FF 01 02 01 FB reads as a status packet with ERROR 0x01 (voltage): the
  // servo's own answer, ERROR 0x00, is the one that counts.
  const BusResult result = transact(*engine_, PingOp{1});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.servo_error, 0x00);
  // The adapter echoes every attempt: one echo, and for each retry a loaded machine made its echo
  // and perhaps the late answer it was made for.
  const auto counters = engine_->counters();
  EXPECT_GE(counters.stray_frames, 1U + counters.retries);
  EXPECT_LE(counters.stray_frames, 1U + 2 * counters.retries);
}

TEST_F(EchoTest, EchoedTwoByteReadIsNotTakenForItsData) {
  // The echo FF FF 02 04 02 03 02 F1 looks like an answer carrying the two bytes {03, 02}.
  const BusResult result = transact(*engine_, ReadOp{2, 3, 2}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x08, 0x2A}));  // sts model 8.42
}

TEST_F(EchoTest, EchoedPingOfAnAbsentServoIsNotTakenForItsAnswer) {
  ASSERT_EQ(transact(*engine_, PingOp{1}).status, BusStatus::Ok);  // the echo and then the answer: it echoes
  const BusResult absent = transact(*engine_, PingOp{9});
  EXPECT_EQ(absent.status, BusStatus::Timeout) << absent.detail;
}

TEST_F(EchoTest, WritesAreAcknowledgedThroughAnEchoingAdapter) {
  const BusResult result = transact(*engine_, WriteOp{1, 42, {0x00, 0x09}});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(simulator_.read_memory(1, 42, 2), (Bytes{0x00, 0x09}));
}

}  // namespace
}  // namespace sms::gateway
