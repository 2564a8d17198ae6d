// The safety supervisor's state (docs/PLC_GUIDE.md "Safety"): what a client reads never disagrees with what
// the motion gates enforce, under e-stops, resets, trips and re-arms on three threads; the latch
// and tripped watchdogs are restored from the state file, and a damaged file latches.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <future>
#include <thread>

#include "gateway/units/safety.h"
#include "gateway/units/state_file.h"
#include "tests/support/bus_test_support.h"
#include "tests/support/processes.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

// The safety state file in a scratch directory of its own.
class TempState {
 public:
  std::string dir() const { return dir_.path(); }
  std::string file() const { return dir_.file("safety.state"); }

 private:
  test::TempDir dir_;
};

// Two buses whose ports do not exist (the supervisor's rules need no servo), each with a short
// watchdog; their engines run, down, so stops fail fast and nothing is owed (no servos).
class SafetyState : public ::testing::Test {
 protected:
  void make(const std::string& state_dir) {
    config_.state_dir = state_dir;
    config_.buses.clear();
    for (const char* name : {"arm", "base"}) {
      config::BusConfig bus;
      bus.name = name;
      bus.device = std::string("/nonexistent/") + name;
      bus.protocol = protocol::BusProtocol::Feetech;
      bus.baud = 1000000;
      config::WatchdogConfig watchdog;
      watchdog.timeout = std::chrono::milliseconds{10};
      bus.watchdog = watchdog;
      config_.buses.push_back(bus);
    }
    engines_.clear();
    gates_.clear();
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

  config::Config config_;
  std::vector<std::shared_ptr<MotionGate>> gates_;
  std::vector<std::unique_ptr<BusEngine>> engines_;
  std::unique_ptr<SafetySupervisor> safety_;
};

TEST_F(SafetyState, WhatAClientReadsNeverDisagreesWithTheGates) {
  make("");
  constexpr auto kFor = 1500ms;
  const auto until = std::chrono::steady_clock::now() + kFor;
  std::atomic<bool> running{true};
  std::atomic<int> estops{0}, rearms{0}, snapshots{0}, disagreements{0};
  auto inline_post = [](std::function<void()> work) { work(); };
  std::thread operator_thread([&] {  // the e-stop set and reset, again and again
    while (std::chrono::steady_clock::now() < until && estops < 400) {
      safety_->estop(inline_post, [](bool) {});
      std::this_thread::sleep_for(std::chrono::microseconds(300 * (estops % 7)));
      safety_->reset_estop();
      ++estops;
    }
    running = false;
  });
  std::thread plc_thread([&] {  // feeds, lets the watchdogs trip, re-arms
    while (running) {
      safety_->feed_write(0);
      safety_->feed_write(1);
      std::this_thread::sleep_for(std::chrono::microseconds(200 * (rearms % 80)));
      safety_->rearm_watchdogs();
      ++rearms;
    }
  });
  while (running) {  // a client reading the discrete inputs and registers
    const SafetyFacts facts = safety_->facts();
    for (const BusSafetyFacts& bus : facts.buses) {
      const bool expected = facts.estop_latched || bus.state == WatchdogState::Tripped;
      if (bus.motion_blocked != expected) ++disagreements;
    }
    ++snapshots;
  }
  operator_thread.join();
  plc_thread.join();
  EXPECT_EQ(disagreements.load(), 0) << "of " << snapshots.load() << " snapshots";
  EXPECT_GT(estops.load(), 50);
  EXPECT_GT(rearms.load(), 20);
  EXPECT_GT(snapshots.load(), 100);
  // Quiet again: nothing latched; every gate says what the state says.
  safety_->rearm_watchdogs();
  const SafetyFacts facts = safety_->facts();
  EXPECT_FALSE(facts.estop_latched);
  for (std::size_t bus = 0; bus < facts.buses.size(); ++bus) {
    EXPECT_EQ(gates_[bus]->blocked(), facts.buses[bus].state == WatchdogState::Tripped);
  }
}

// A bus lent to commissioning refuses motion until it is returned, whatever else happens: an
// e-stop reset or a re-arm does not release it, the other bus is untouched, and the stop it
// performed is said in the cause register. A restart does not remember it: the bus runs again.
TEST_F(SafetyState, ALentBusRefusesMotionUntilReturned) {
  TempState state;
  make(state.dir());
  std::promise<bool> stopped;
  safety_->lend_bus(0, "the test", [&](bool ok) { stopped.set_value(ok); });
  auto sent = stopped.get_future();
  ASSERT_EQ(sent.wait_for(5s), std::future_status::ready) << "the stop's frames were never sent";
  const auto refused = safety_->admit_motion(0);
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().find("lent to commissioning"), std::string::npos) << refused.error();
  EXPECT_TRUE(safety_->admit_motion(1));
  auto inline_post = [](std::function<void()> work) { work(); };
  safety_->estop(inline_post, [](bool) {});
  safety_->reset_estop();
  safety_->rearm_watchdogs();
  SafetyFacts facts = safety_->facts();
  EXPECT_TRUE(facts.buses[0].lent);
  EXPECT_TRUE(facts.buses[0].motion_blocked);
  EXPECT_FALSE(facts.buses[1].lent);
  EXPECT_TRUE(gates_[0]->blocked());
  EXPECT_FALSE(safety_->admit_motion(0));

  safety_->return_bus(0, "the test");
  facts = safety_->facts();
  EXPECT_FALSE(facts.buses[0].lent);
  EXPECT_FALSE(gates_[0]->blocked());
  EXPECT_TRUE(safety_->admit_motion(0));

  // Stopping the gateway skips a lent bus's on_stop: its servos were stopped when it was lent.
  std::promise<bool> lent_again;
  safety_->lend_bus(0, "the test", [&](bool ok) { lent_again.set_value(ok); });
  ASSERT_EQ(lent_again.get_future().wait_for(5s), std::future_status::ready);
  safety_->stop_for_shutdown(2s);
  facts = safety_->facts();
  EXPECT_EQ(facts.buses[0].last_cause, StopCause::Commissioning);
  EXPECT_EQ(facts.buses[1].last_cause, StopCause::Shutdown);
  TearDown();
  make(state.dir());
  EXPECT_FALSE(safety_->facts().buses[0].lent);
  EXPECT_TRUE(safety_->admit_motion(0));
}

TEST_F(SafetyState, LatchAndTripsAreRestoredFromTheStateFile) {
  TempState state;
  { std::ofstream(state.file()) << "estop_latched: true\ntripped_watchdogs: [base, gone]\n"; }
  make(state.dir());
  const SafetyFacts facts = safety_->facts();
  EXPECT_TRUE(facts.estop_latched);
  EXPECT_EQ(facts.buses[0].state, WatchdogState::Armed);
  EXPECT_EQ(facts.buses[1].state, WatchdogState::Tripped);
  EXPECT_TRUE(gates_[0]->blocked());
  EXPECT_TRUE(gates_[1]->blocked());
  EXPECT_EQ(safety_->state_file(), state.file());
  EXPECT_FALSE(safety_->admit_motion(0));

  safety_->reset_estop();
  EXPECT_FALSE(gates_[0]->blocked());
  EXPECT_TRUE(gates_[1]->blocked());  // still tripped
  auto text = read_state_file(state.file());
  ASSERT_TRUE(text && text->has_value());
  EXPECT_NE((*text)->find("estop_latched: false"), std::string::npos) << **text;
  EXPECT_NE((*text)->find("[base]"), std::string::npos) << **text;

  safety_->rearm_watchdogs();
  EXPECT_FALSE(gates_[1]->blocked());
  text = read_state_file(state.file());
  EXPECT_NE((*text)->find("tripped_watchdogs: []"), std::string::npos) << **text;
}

TEST_F(SafetyState, ADamagedStateFileLatchesTheEStop) {
  TempState state;
  { std::ofstream(state.file()) << "estop_latched: [unclosed\n"; }
  make(state.dir());
  EXPECT_TRUE(safety_->facts().estop_latched);
  EXPECT_TRUE(gates_[0]->blocked());
}

TEST_F(SafetyState, AStateDirThatDoesNotExistIsRefusedWithWhatToDo) {
  try {
    make("/nonexistent/state");
    FAIL() << "accepted";
  } catch (const std::runtime_error& error) {
    EXPECT_NE(std::string(error.what()).find("state_dir /nonexistent/state: No such file or directory; create it"),
              std::string::npos)
        << error.what();
  }
}

TEST(StateFile, IsReplacedWholeAndAMissingFileIsNoError) {
  TempState state;
  EXPECT_EQ(read_state_file(state.file())->has_value(), false);
  ASSERT_TRUE(write_file_atomically(state.file(), "one\n"));
  ASSERT_TRUE(write_file_atomically(state.file(), "two\n"));
  EXPECT_EQ(read_state_file(state.file())->value(), "two\n");
  EXPECT_FALSE(std::filesystem::exists(state.file() + ".new"));
  const auto refused = write_file_atomically("/nonexistent/dir/file", "x");
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().find("cannot create /nonexistent/dir/file.new"), std::string::npos) << refused.error();
}

}  // namespace
}  // namespace sms::gateway
