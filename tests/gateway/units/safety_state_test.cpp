// The safety supervisor's state (docs/PLC_GUIDE.md "Safety"): what a client reads never disagrees with what
// the motion gates enforce, under e-stops, resets, trips and re-arms on three threads; the latch,
// tripped watchdogs and owed stops are restored from the state file (docs/SAFETY.md "What
// survives a restart"), anything but a complete state of the exact schema latches with the
// reason, and a state that cannot be saved shows until a save succeeds.
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
// watchdog; their engines run, down, so stops fail fast. Without `servo` nothing is owed (no
// servos); with it, servo 1 (sts) on bus arm is owed every stop.
class SafetyState : public ::testing::Test {
 protected:
  void make(const std::string& state_dir, bool servo = false) {
    config_.state_dir = state_dir;
    config_.servos.clear();
    if (servo) {
      config::ServoConfig sts;
      sts.unit_id = 1;
      sts.bus = "arm";
      sts.bus_index = 0;
      sts.servo_id = 1;
      sts.table = modbus_map::TableId::Sts;
      config_.servos.push_back(sts);
    }
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

  testing::LogCapture log_;  // first: it outlives every thread that logs
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
  // That motion write started bus 0's 10 ms watchdog: let it trip and re-arm it, so no trip can
  // come between the lend below and the end (the cause register would say watchdog).
  ASSERT_TRUE(test::eventually([&] { return safety_->facts().buses[0].state == WatchdogState::Tripped; }));
  safety_->rearm_watchdogs();

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

// motion_refusal() names the rule that refuses a motion write (the console asks it after a 0x04)
// in admit_motion()'s words, and starts no watchdog: asking is not a motion write.
TEST_F(SafetyState, MotionRefusalNamesTheRuleAndStartsNothing) {
  make("", true);
  EXPECT_FALSE(safety_->motion_refusal(0, 1));
  EXPECT_EQ(safety_->facts().buses[0].state, WatchdogState::Armed);  // asking started no count
  EXPECT_FALSE(safety_->facts().buses[0].since_trip);
  auto inline_post = [](std::function<void()> work) { work(); };
  safety_->estop(inline_post, [](bool) {});
  const auto latched = safety_->motion_refusal(1);
  ASSERT_TRUE(latched);
  EXPECT_EQ(*latched, safety_->admit_motion(1).error());
  EXPECT_NE(latched->find("bus base: the e-stop is latched"), std::string::npos) << *latched;
  safety_->reset_estop();
  // The e-stop's stop reached no servo (the port is missing): servo 1 owes it.
  ASSERT_TRUE(test::eventually([&] { return safety_->facts().buses[0].owed_stops == 1; }, "servo 1 owed its stop"));
  const auto owed = safety_->motion_refusal(0, 1);
  ASSERT_TRUE(owed);
  EXPECT_NE(owed->find("servo 1 owes a safe stop (e-stop)"), std::string::npos) << *owed;
  EXPECT_FALSE(safety_->motion_refusal(0, 2));
  EXPECT_FALSE(safety_->motion_refusal(0));
  // A motion write starts bus arm's 10 ms watchdog; once it tripped, that is the rule.
  ASSERT_TRUE(safety_->admit_motion(0));
  ASSERT_TRUE(test::eventually([&] { return safety_->facts().buses[0].state == WatchdogState::Tripped; }, "the trip"));
  const auto tripped = safety_->motion_refusal(0, 1);
  ASSERT_TRUE(tripped);
  EXPECT_NE(tripped->find("bus arm: its watchdog tripped (no feed for 10 ms)"), std::string::npos) << *tripped;
  EXPECT_TRUE(safety_->facts().buses[0].since_trip);
  EXPECT_FALSE(safety_->motion_refusal(1));
  safety_->rearm_watchdogs();
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

// Every way a state file can be damaged that a tester found, and a few more: each latches, and
// the log says what is wrong, with which file, and what to do.
struct DamagedState {
  std::string name;
  std::string text;
  std::string reason;  // in the parser's error and the log line
};
void PrintTo(const DamagedState& damaged, std::ostream* out) { *out << damaged.name; }

const std::vector<DamagedState> kDamagedStates{
    {"Empty", "", "it is empty"},
    {"OnlyAComment", "# nothing else\n", "it is empty"},
    {"CutMidValue", "estop_latched: tr", "it misses the key `tripped_watchdogs`"},
    {"CutMidValueVersion2", "version: 2\nestop_latched: tr", "it misses the key `tripped_watchdogs`"},
    {"CutAfterALine", "version: 2\nestop_latched: false\ntripped_watchdogs: []\n", "it misses the key `owed_stops`"},
    {"CutKey", "estop_la", "it is `estop_la`, not a map of its keys"},
    {"UnknownKeysOnly", "colour: blue\nsize: 3\n", "it has an unknown key `colour`"},
    {"MisspeltKey", "estop_latch: true\n", "it has an unknown key `estop_latch`"},
    {"ExtraKey", "version: 2\nestop_latched: false\ntripped_watchdogs: []\nowed_stops: []\nnote: hi\n",
     "it has an unknown key `note`"},
    {"RepeatedKey", "estop_latched: false\nestop_latched: true\ntripped_watchdogs: []\n",
     "it has the key `estop_latched` twice"},
    {"NotABoolean", "estop_latched: maybe\ntripped_watchdogs: []\n", "estop_latched is `maybe`, not true or false"},
    {"YesIsNotABoolean", "estop_latched: yes\ntripped_watchdogs: []\n", "estop_latched is `yes`, not true or false"},
    {"QuotedBoolean", "estop_latched: \"false\"\ntripped_watchdogs: []\n",
     "estop_latched is `false` (quoted or tagged), not true or false"},
    {"AList", "- estop_latched\n- false\n", "it is a list, not a map of its keys"},
    {"TrippedNotAList", "estop_latched: false\ntripped_watchdogs: arm\n",
     "tripped_watchdogs is `arm`, not a list of bus names"},
    {"Unbalanced", "estop_latched: [unclosed\n", "it is not YAML"},
    {"RandomBytes", std::string("\x9c\x01\xfe\x7f{[:\x03", 8), "it is"},
    {"NulBytes", std::string(16, '\0'), "it is"},
    {"TwoDocuments", "estop_latched: false\ntripped_watchdogs: []\n---\nestop_latched: true\n",
     "it holds 2 YAML documents, not one"},
    {"NewerVersion", "version: 3\nestop_latched: false\ntripped_watchdogs: []\nowed_stops: []\n",
     "its version is `3`; this gateway reads version 2"},
    {"OwedServoOutOfRange",
     "version: 2\nestop_latched: false\ntripped_watchdogs: []\nowed_stops: [{bus: arm, servo: 300, why: e-stop, "
     "answers_writes: true}]\n",
     "owed_stops[0].servo is `300`, not a whole number from 0 to 253"},
    {"OwedStopMissesAKey",
     "version: 2\nestop_latched: false\ntripped_watchdogs: []\nowed_stops: [{bus: arm, servo: 1}]\n",
     "owed_stops[0] misses the key `why`"},
};

class DamagedStateFile : public SafetyState, public ::testing::WithParamInterface<DamagedState> {};

TEST_P(DamagedStateFile, IsRefusedWithItsReason) {
  const auto parsed = parse_safety_state(GetParam().text);
  ASSERT_FALSE(parsed) << "accepted as a state";
  EXPECT_NE(parsed.error().find(GetParam().reason), std::string::npos) << parsed.error();
}

TEST_P(DamagedStateFile, LatchesTheEStopAndSaysWhyWhereAndWhatToDo) {
  TempState state;
  { std::ofstream(state.file(), std::ios::binary) << GetParam().text; }
  make(state.dir());
  EXPECT_TRUE(safety_->facts().estop_latched);
  EXPECT_TRUE(gates_[0]->blocked());
  EXPECT_TRUE(gates_[1]->blocked());
  EXPECT_TRUE(log_.contains(state.file() + " is not a complete safety state: " + GetParam().reason)) << log_.text();
  EXPECT_TRUE(log_.contains("the e-stop is LATCHED as a precaution")) << log_.text();
  EXPECT_TRUE(log_.contains("then reset the e-stop (gateway unit coil 1 := 0)")) << log_.text();
  // The reset writes a complete state in place of the damaged one.
  safety_->reset_estop();
  const auto text = read_state_file(state.file());
  ASSERT_TRUE(text && text->has_value());
  const auto written = parse_safety_state(**text);
  ASSERT_TRUE(written) << written.error();
  EXPECT_FALSE(written->estop_latched);
}

INSTANTIATE_TEST_SUITE_P(EveryDamage, DamagedStateFile, ::testing::ValuesIn(kDamagedStates),
                         [](const ::testing::TestParamInfo<DamagedState>& info) { return info.param.name; });

// A directory where the file should be cannot be read as a state: latched, and the log says to
// remove it.
TEST_F(SafetyState, AStateFileThatIsADirectoryLatches) {
  TempState state;
  std::filesystem::create_directory(state.file());
  make(state.dir());
  EXPECT_TRUE(safety_->facts().estop_latched);
  EXPECT_TRUE(log_.contains(state.file() + " is not a regular file (a directory); remove it")) << log_.text();
  EXPECT_TRUE(log_.contains("the e-stop is LATCHED as a precaution")) << log_.text();
}

// No file at all is a first start: nothing latched, nothing said about damage.
TEST_F(SafetyState, AMissingStateFileIsAFirstStart) {
  TempState state;
  make(state.dir());
  EXPECT_FALSE(safety_->facts().estop_latched);
  EXPECT_FALSE(gates_[0]->blocked());
  EXPECT_FALSE(log_.contains("LATCHED")) << log_.text();
}

// Names the configuration no longer has are stale, not damage: a warning each, nothing latched.
TEST_F(SafetyState, StaleBusAndServoNamesAreWarningsNotDamage) {
  TempState state;
  {
    std::ofstream(state.file()) << "version: 2\nestop_latched: false\ntripped_watchdogs: [gone]\n"
                                   "owed_stops: [{bus: gone, servo: 1, why: e-stop, answers_writes: true}, "
                                   "{bus: arm, servo: 9, why: watchdog, answers_writes: true}]\n";
  }
  make(state.dir(), true);
  const SafetyFacts facts = safety_->facts();
  EXPECT_FALSE(facts.estop_latched);
  EXPECT_EQ(facts.buses[0].owed_stops, 0u);
  EXPECT_FALSE(gates_[0]->blocked());
  EXPECT_TRUE(log_.contains("names a tripped watchdog on bus `gone`, which has none now: ignored")) << log_.text();
  EXPECT_TRUE(
      log_.contains("servo 1 on bus `gone` was owed its safe stop (e-stop), but the configuration has no such "
                    "servo now: ignored"))
      << log_.text();
  EXPECT_TRUE(log_.contains("servo 9 on bus `arm`")) << log_.text();
}

TEST(SafetyStateFile, RoundTripsEveryKey) {
  const SafetyStateRecord state{
      true,
      {"arm", "base"},
      {OwedStopRecord{"arm", 1, "e-stop", true}, OwedStopRecord{"arm", 253, "the gateway is stopping", false},
       OwedStopRecord{"yes", 0, "watchdog", true}}};
  const std::string text = render_safety_state(state);
  const auto parsed = parse_safety_state(text);
  ASSERT_TRUE(parsed) << parsed.error() << "\n" << text;
  EXPECT_EQ(*parsed, state) << text;
  EXPECT_NE(text.find("version: 2\n"), std::string::npos) << text;
  const auto empty = parse_safety_state(render_safety_state({}));
  ASSERT_TRUE(empty) << empty.error();
  EXPECT_EQ(*empty, SafetyStateRecord{});
}

// Files written before owed stops were kept (no version key, exactly two keys) are still read.
TEST(SafetyStateFile, Version1IsStillRead) {
  const auto parsed = parse_safety_state("# old\nestop_latched: true\ntripped_watchdogs: [arm]\n");
  ASSERT_TRUE(parsed) << parsed.error();
  EXPECT_TRUE(parsed->estop_latched);
  EXPECT_EQ(parsed->tripped_watchdogs, std::vector<std::string>{"arm"});
  EXPECT_TRUE(parsed->owed_stops.empty());
}

// An owed stop read back goes into the engine as owed again (servo 1's torque off, refusing its
// motion), and stays in the file until the servo takes it.
TEST_F(SafetyState, OwedStopsAreRestoredIntoTheEngineAndKept) {
  TempState state;
  {
    std::ofstream(state.file()) << "version: 2\nestop_latched: false\ntripped_watchdogs: []\n"
                                   "owed_stops: [{bus: arm, servo: 1, why: e-stop, answers_writes: false}]\n";
  }
  make(state.dir(), true);
  EXPECT_FALSE(safety_->facts().estop_latched);
  EXPECT_EQ(safety_->facts().buses[0].owed_stops, 1u);
  const auto owed = engines_[0]->owed_stops();
  ASSERT_EQ(owed.size(), 1u);
  EXPECT_EQ(owed[0].write.servo_id, 1);
  EXPECT_EQ(owed[0].write.address, 40);  // sts torque_enable := 0
  EXPECT_EQ(owed[0].write.data, protocol::Bytes{0});
  EXPECT_FALSE(owed[0].write.expect_reply);
  EXPECT_EQ(owed[0].why, "e-stop");
  EXPECT_TRUE(log_.contains("servo 1 was owed its safe stop (e-stop) before the restart")) << log_.text();

  safety_->rearm_watchdogs();  // nothing tripped: writes nothing
  auto inline_post = [](std::function<void()> work) { work(); };
  std::promise<bool> latched;
  safety_->estop(inline_post, [&](bool ok) { latched.set_value(ok); });
  ASSERT_EQ(latched.get_future().wait_for(5s), std::future_status::ready) << "the e-stop was never answered";
  safety_->reset_estop();
  const auto text = read_state_file(state.file());
  ASSERT_TRUE(text && text->has_value());
  const auto kept = parse_safety_state(**text);
  ASSERT_TRUE(kept) << kept.error();
  ASSERT_EQ(kept->owed_stops.size(), 1u) << **text;
  EXPECT_EQ(kept->owed_stops[0].servo, 1);
}

// A stop that becomes owed is written at once, without any other change to the state.
TEST_F(SafetyState, AStopThatBecomesOwedIsWritten) {
  TempState state;
  make(state.dir(), true);
  std::promise<bool> stopped;
  safety_->lend_bus(0, "the test", [&](bool ok) { stopped.set_value(ok); });  // not itself kept
  auto sent = stopped.get_future();
  ASSERT_EQ(sent.wait_for(5s), std::future_status::ready);
  EXPECT_FALSE(sent.get()) << "the bus is down: the stop cannot have reached servo 1";
  EXPECT_TRUE(test::eventually(
      [&] {
        const auto text = read_state_file(state.file());
        if (!text || !text->has_value()) return false;
        const auto kept = parse_safety_state(**text);
        return kept && kept->owed_stops == std::vector<OwedStopRecord>{{"arm", 1, "commissioning", true}};
      },
      "servo 1's owed stop in " + state.file()));
}

// state_dir stops being writable while the gateway runs (its path is a regular file now: even
// root cannot create a file under it): the e-stop still works, the state shows as not persisted
// with the reason, and the next retry after the directory is back saves it and clears that.
TEST_F(SafetyState, AStateThatCannotBeSavedShowsUntilASaveSucceeds) {
  TempState state;
  const std::string dir = state.dir() + "/state";
  std::filesystem::create_directory(dir);
  make(dir);
  EXPECT_FALSE(safety_->facts().state_not_persisted);
  std::filesystem::rename(dir, dir + ".away");
  { std::ofstream(dir) << "not a directory\n"; }

  auto inline_post = [](std::function<void()> work) { work(); };
  std::promise<bool> latched;
  safety_->estop(inline_post, [&](bool ok) { latched.set_value(ok); });
  auto answered = latched.get_future();
  ASSERT_EQ(answered.wait_for(5s), std::future_status::ready) << "the e-stop was never answered";
  SafetyFacts facts = safety_->facts();
  EXPECT_TRUE(facts.estop_latched);
  EXPECT_TRUE(gates_[0]->blocked());
  EXPECT_TRUE(facts.state_not_persisted);
  EXPECT_NE(facts.state_problem.find("Not a directory"), std::string::npos) << facts.state_problem;
  EXPECT_TRUE(log_.contains("SAFETY STATE NOT PERSISTED")) << log_.text();

  std::filesystem::remove(dir);
  std::filesystem::rename(dir + ".away", dir);
  EXPECT_TRUE(test::eventually([&] { return !safety_->facts().state_not_persisted; }, "a retried save"));
  EXPECT_TRUE(log_.contains("the safety state is kept in " + dir + "/safety.state again")) << log_.text();
  const auto text = read_state_file(dir + "/safety.state");
  ASSERT_TRUE(text && text->has_value());
  const auto kept = parse_safety_state(**text);
  ASSERT_TRUE(kept) << kept.error();
  EXPECT_TRUE(kept->estop_latched);
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
