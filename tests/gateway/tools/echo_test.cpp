// The integrator tools run the engine's transactor (tests/gateway/bus/echo_test.cpp), so they
// see through an adapter's echo the same way.
#include <gtest/gtest.h>

#include <chrono>
#include <memory>

#include "gateway/tools/tool_link.h"
#include "protocol/packet.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"
#include "tests/support/echoing_adapter.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using protocol::Bytes;
using test::EchoingAdapter;
using testing::simulated_servos;

class ToolLinkEchoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    simulator_.start();
    adapter_ = std::make_unique<EchoingAdapter>(simulator_.slave_path(), 1'000'000);
  }
  void TearDown() override {
    adapter_.reset();
    simulator_.stop();
  }
  simulator::SimulatedBus simulator_{simulated_servos({1, 2})};
  std::unique_ptr<EchoingAdapter> adapter_;
};

// The integrator tools run the engine's transactor, so they see through the echo the same way:
// the echo of a PING to an absent ID is nobody's answer (not even "something was heard", which
// would tell the scan a servo collided there).
TEST_F(ToolLinkEchoTest, ToolLinkSeesThroughTheEchoLikeTheEngine) {
  LinkSettings settings;
  settings.device = adapter_->host_path();
  settings.protocol = protocol::BusProtocol::Feetech;
  settings.baud = 1'000'000;
  // Long enough that no PING is asked twice, even under ThreadSanitizer on a loaded machine: the
  // answer to a PING asked again comes after the first one's and lands in the next PING's wait,
  // where the link rightly reports it as another ID heard (20 ms here failed that way under TSan).
  settings.latency = 200ms;
  const auto link = make_servo_link(settings);
  const auto opened = link->open();
  ASSERT_TRUE(opened) << opened.error();

  const LinkAnswer present = link->ping(1);
  EXPECT_EQ(present.status, LinkStatus::Ok) << present.detail;
  EXPECT_EQ(present.servo_status, 0x00);  // the servo's answer, not the echo's "ERROR 0x01"
  const LinkAnswer absent = link->ping(9);
  EXPECT_EQ(absent.status, LinkStatus::Timeout) << absent.detail;
  EXPECT_FALSE(absent.heard_anything);
  EXPECT_TRUE(absent.other_ids.empty());
  // Both servos answer a broadcast PING at once: their answers collide, but someone is there.
  const LinkAnswer anyone = link->ping(protocol::kBroadcastId);
  EXPECT_TRUE(anyone.heard_anything) << anyone.detail;
  const LinkAnswer model = link->read(2, 3, 2);
  ASSERT_EQ(model.status, LinkStatus::Ok) << model.detail;
  EXPECT_EQ(model.data, (Bytes{0x08, 0x2A}));
}

}  // namespace
}  // namespace sms::gateway
