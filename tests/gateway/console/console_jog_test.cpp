// The hold-to-run rule (gateway/console/console_jog.h) against a real SafetySupervisor: a jog
// session pressed before an e-stop latch or a watchdog trip of its bus is over for good, even when
// the latch was reset or the watchdog re-armed before the session looked; the page is told which;
// a press while motion is blocked moves nothing; a new press after the reset moves again.
#include "gateway/console/console_jog.h"

#include <gtest/gtest.h>

#include <chrono>
#include <future>
#include <memory>
#include <string>
#include <vector>

#include "gateway/units/safety.h"
#include "tests/support/await.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway::console {
namespace {

using namespace std::chrono_literals;

// Two buses whose ports do not exist (the rule needs no servo; their stops fail fast): `arm` with
// a 20 ms watchdog fed by any write, `base` without one.
class JogSessionRule : public ::testing::Test {
 protected:
  void SetUp() override {
    for (const char* name : {"arm", "base"}) {
      config::BusConfig bus;
      bus.name = name;
      bus.device = std::string("/nonexistent/") + name;
      bus.protocol = protocol::BusProtocol::Feetech;
      bus.baud = 1000000;
      if (bus.name == "arm") {
        config::WatchdogConfig watchdog;
        watchdog.timeout = 20ms;
        bus.watchdog = watchdog;
      }
      config_.buses.push_back(bus);
    }
    std::vector<BusEngine*> engines;
    for (const auto& bus : config_.buses) {
      gates_.push_back(std::make_shared<MotionGate>());
      BusSettings settings = testing::bus_settings(bus.device, {});
      settings.name = bus.name;
      settings.motion_gate = gates_.back();
      engines_.push_back(make_bus_engine(settings));
      engines_.back()->start();
      engines.push_back(engines_.back().get());
    }
    safety_ = std::make_unique<SafetySupervisor>(config_, engines, gates_);
    safety_->start();
  }
  void TearDown() override {
    safety_.reset();
    for (auto& engine : engines_) engine->stop();
  }

  Expected<JogSession> press(std::size_t bus) {
    return JogSession::press(bus, config_.buses.at(bus).name, safety_->motion_stops(bus));
  }
  std::optional<std::string> ended(const JogSession& session) {
    return session.ended(safety_->motion_stops(session.bus()));
  }
  // Gateway unit coil 1 := 1, as the io thread runs it; returns once the stop frames were tried.
  void latch() {
    auto done = std::make_shared<std::promise<void>>();
    auto finished = done->get_future();
    safety_->estop([](std::function<void()> work) { work(); }, [done](bool) { done->set_value(); }, "the test");
    ASSERT_EQ(finished.wait_for(10s), std::future_status::ready) << "the e-stop's stop did not finish";
  }
  void trip_arm() {
    ASSERT_TRUE(safety_->admit_motion(0)) << "a motion write on arm was refused";  // starts its watchdog
    ASSERT_TRUE(sms::test::poll_until([&] { return safety_->motion_stops(0).tripped; }))
        << sms::test::await_failure("arm's 20 ms watchdog to trip", sms::test::kAwaitTimeout);
  }

  config::Config config_;
  std::vector<std::shared_ptr<MotionGate>> gates_;
  std::vector<std::unique_ptr<BusEngine>> engines_;
  std::unique_ptr<SafetySupervisor> safety_;
};

TEST_F(JogSessionRule, ALatchResetBeforeTheSessionLooksEndsItForGood) {
  auto session = press(1);
  ASSERT_TRUE(session) << session.error();
  EXPECT_FALSE(ended(*session));
  latch();
  safety_->reset_estop("the test");
  // Nothing is latched or blocked any more; the session still sees that a latch came.
  EXPECT_FALSE(safety_->motion_stops(1).blocked);
  const auto why = ended(*session);
  ASSERT_TRUE(why);
  EXPECT_EQ(why->rfind("ended by the e-stop", 0), 0u) << *why;
  EXPECT_EQ(ended(*session), why) << "an ended session stays ended";
  // A new press moves again.
  auto again = press(1);
  ASSERT_TRUE(again) << again.error();
  EXPECT_FALSE(ended(*again));
}

TEST_F(JogSessionRule, AStillLatchedEStopEndsTheSessionOnEveryBus) {
  auto on_arm = press(0);
  auto on_base = press(1);
  ASSERT_TRUE(on_arm && on_base);
  latch();
  for (const auto* session : {&*on_arm, &*on_base}) {
    const auto why = ended(*session);
    ASSERT_TRUE(why);
    EXPECT_EQ(why->rfind("ended by the e-stop", 0), 0u) << *why;
  }
  safety_->reset_estop("the test");
}

TEST_F(JogSessionRule, APressWhileMotionIsBlockedMovesNothing) {
  latch();
  const auto refused = press(1);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error(), "the e-stop is latched: reset it first; not moved");
  safety_->reset_estop("the test");
  EXPECT_TRUE(press(1));

  trip_arm();
  const auto tripped = press(0);
  ASSERT_FALSE(tripped);
  EXPECT_NE(tripped.error().find("the watchdog of bus arm tripped"), std::string::npos) << tripped.error();
  EXPECT_TRUE(press(1)) << "bus base has no watchdog; arm's trip does not block it";
  safety_->rearm_watchdogs("the test");
}

TEST_F(JogSessionRule, ATripReArmedBeforeTheSessionLooksEndsOnlyTheSessionsOfItsBus) {
  auto on_arm = press(0);
  auto on_base = press(1);
  ASSERT_TRUE(on_arm && on_base);
  trip_arm();
  safety_->rearm_watchdogs("the test");
  EXPECT_FALSE(safety_->motion_stops(0).blocked);
  const auto why = ended(*on_arm);
  ASSERT_TRUE(why);
  EXPECT_EQ(why->rfind("ended by the watchdog of bus arm", 0), 0u) << *why;
  EXPECT_FALSE(ended(*on_base)) << "a trip of bus arm ended a jog on bus base";
  EXPECT_TRUE(press(0)) << "a new press after the re-arm is refused";
}

TEST_F(JogSessionRule, ALentBusEndsItsSessions) {
  auto session = press(1);
  ASSERT_TRUE(session);
  auto lent = std::make_shared<std::promise<void>>();
  auto finished = lent->get_future();
  safety_->lend_bus(1, "the test", [lent](bool) { lent->set_value(); });
  ASSERT_EQ(finished.wait_for(10s), std::future_status::ready);
  EXPECT_EQ(ended(*session), "ended: bus base was stopped for commissioning");
  EXPECT_FALSE(press(1));
  safety_->return_bus(1, "the test");
  EXPECT_TRUE(ended(*session)) << "the bus came back, the session stays over";
  EXPECT_TRUE(press(1));
}

}  // namespace
}  // namespace sms::gateway::console
