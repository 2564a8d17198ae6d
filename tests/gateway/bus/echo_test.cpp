// An RS-485 adapter without echo suppression hands the host its own frame back before the
// servo's answer. Here a relay between the engine's pty and the simulator's pty plays that
// adapter: everything the engine sends goes to the (real, simulated) servos and straight back.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cstdlib>
#include <thread>

#include "tests/support/bus_test_support.h"
#include "gateway/tools/tool_link.h"
#include "simulator/serial_line.h"

namespace sms::gateway {
namespace {

using namespace testing;
using namespace std::chrono_literals;
using protocol::Bytes;

class EchoingAdapter {
 public:
  // `line` is the simulator's slave path; the engine opens host_path().
  EchoingAdapter(const std::string& line, std::uint32_t baud) {
    host_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (host_ < 0 || ::grantpt(host_) != 0 || ::unlockpt(host_) != 0) throw std::runtime_error("no pty");
    host_path_ = ::ptsname(host_);
    line_ = ::open(line.c_str(), O_RDWR | O_NOCTTY);
    if (line_ < 0) throw std::runtime_error("cannot open " + line);
    simulator::configure_raw_serial(line_, baud);
    relay_ = std::thread([this] { run(); });
  }
  ~EchoingAdapter() {
    stop_ = true;
    relay_.join();
    ::close(line_);
    ::close(host_);
  }
  const std::string& host_path() const { return host_path_; }

 private:
  void run() {
    std::array<std::uint8_t, 512> buffer{};
    while (!stop_) {
      std::array<pollfd, 2> fds{{{host_, POLLIN, 0}, {line_, POLLIN, 0}}};
      if (::poll(fds.data(), fds.size(), 5) <= 0) continue;
      if ((fds[0].revents & POLLIN) != 0) {
        const ssize_t n = ::read(host_, buffer.data(), buffer.size());
        if (n > 0) {
          [[maybe_unused]] const auto echoed = ::write(host_, buffer.data(), static_cast<std::size_t>(n));
          [[maybe_unused]] const auto sent = ::write(line_, buffer.data(), static_cast<std::size_t>(n));
        }
      }
      if ((fds[1].revents & POLLIN) != 0) {
        const ssize_t n = ::read(line_, buffer.data(), buffer.size());
        if (n > 0) [[maybe_unused]] const auto passed = ::write(host_, buffer.data(), static_cast<std::size_t>(n));
      }
    }
  }

  int host_ = -1;
  int line_ = -1;
  std::string host_path_;
  std::atomic<bool> stop_{false};
  std::thread relay_;
};

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
  EXPECT_EQ(engine_->counters().stray_frames, 1U);
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

// The integrator tools run the engine's transactor, so they see through the echo the same way:
// the echo of a PING to an absent ID is nobody's answer (not even "something was heard", which
// would tell the scan a servo collided there).
TEST_F(EchoTest, ToolLinkSeesThroughTheEchoLikeTheEngine) {
  engine_->stop();  // one program on the line at a time: the port is opened exclusively
  LinkSettings settings;
  settings.device = adapter_->host_path();
  settings.protocol = protocol::BusProtocol::Feetech;
  settings.baud = 1'000'000;
  settings.latency = 20ms;  // a pty, a relay thread and the simulator on 2 shared cores
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
