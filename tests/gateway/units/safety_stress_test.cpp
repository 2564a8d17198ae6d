// "Motion blocked" as a client reads it, while it changes on other threads (docs/PLC_GUIDE.md
// "Safety"): the e-stop latched and reset again and again on one thread, real watchdog trips and
// re-arms on another, and a client reading the gateway unit's discrete inputs and input registers
// through the UnitRouter with Modbus PDUs on a third. No answer may disagree with itself: motion
// blocked exactly when the e-stop is latched or a watchdog tripped. Bounded in iterations and
// time; part of the ThreadSanitizer run (the suite's name matches its SafetyState pattern).
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gateway/units/safety.h"
#include "gateway/units/unit_router.h"
#include "tests/support/await.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

// Keeps the answer a request got (the gateway unit answers these reads before handle() returns).
class Answer final : public Reply::Target {
 public:
  void deliver(std::uint64_t, Bytes response_pdu) override { pdu = std::move(response_pdu); }
  Bytes pdu;
};

// Two buses whose ports do not exist (no servo is needed for the rules; their stops fail fast),
// each with a 10 ms watchdog fed by any write, the supervisor and the unit router over them.
class SafetyStateUnderLoad : public ::testing::Test {
 protected:
  void SetUp() override {
    for (const char* name : {"arm", "base"}) {
      config::BusConfig bus;
      bus.name = name;
      bus.device = std::string("/nonexistent/") + name;
      bus.protocol = protocol::BusProtocol::Feetech;
      bus.baud = 1000000;
      config::WatchdogConfig watchdog;
      watchdog.timeout = 10ms;
      bus.watchdog = watchdog;
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
    catalog_ = std::make_unique<UnitCatalog>(config_);
    router_ = std::make_unique<UnitRouter>(config_, *catalog_, engines, inline_post(), *safety_);
  }
  void TearDown() override {
    router_.reset();
    safety_.reset();
    for (auto& engine : engines_) engine->stop();
  }

  static PostFn inline_post() {
    return [](std::function<void()> work) { work(); };
  }
  // One request to the gateway unit, as a client sends it; its answer PDU.
  Bytes ask(const Bytes& pdu) {
    auto answer = std::make_shared<Answer>();
    router_->handle(config_.modbus_tcp.gateway_unit_id, pdu, Reply(answer, ++serial_));
    return answer->pdu;
  }
  // FC02 discrete inputs 0-3: e-stop latched, a watchdog tripped, motion blocked, a stop owed.
  struct DiscreteInputs {
    bool estop = false, tripped = false, blocked = false, owed = false;
  };
  DiscreteInputs discrete_inputs() {
    const Bytes answer = ask({0x02, 0x00, 0x00, 0x00, 0x04});
    EXPECT_EQ(answer.size(), 3u);
    if (answer.size() != 3) return {};
    const std::uint8_t bits = answer[2];
    return {(bits & 1) != 0, (bits & 2) != 0, (bits & 4) != 0, (bits & 8) != 0};
  }
  // FC04 input registers 10-119 in one request: 10 e-stop latched, bus 0's block at 100 (110 its
  // watchdog state, 118 its motion blocked).
  std::vector<std::uint16_t> input_registers_10_to_119() {
    const Bytes answer = ask({0x04, 0x00, 10, 0x00, 110});
    EXPECT_EQ(answer.size(), 2u + 2 * 110) << "exception " << (answer.size() > 1 ? int(answer[1]) : -1);
    std::vector<std::uint16_t> values;
    for (std::size_t at = 2; at + 1 < answer.size(); at += 2) {
      values.push_back(static_cast<std::uint16_t>(answer[at] << 8 | answer[at + 1]));
    }
    return values;
  }

  config::Config config_;
  std::vector<std::shared_ptr<MotionGate>> gates_;
  std::vector<std::unique_ptr<BusEngine>> engines_;
  std::unique_ptr<SafetySupervisor> safety_;
  std::unique_ptr<UnitCatalog> catalog_;
  std::unique_ptr<UnitRouter> router_;
  std::uint64_t serial_ = 0;
};

TEST_F(SafetyStateUnderLoad, AClientsReadsNeverDisagreeWhileTheEStopAndTheWatchdogsChangeOnOtherThreads) {
  const auto until = std::chrono::steady_clock::now() + 1500ms;
  std::atomic<bool> running{true};
  std::atomic<int> estops{0}, trip_rounds{0};
  std::atomic<bool> trip_missed{false}, stop_unanswered{false};

  std::thread operator_thread([&] {  // latches, waits for the stop to be done, resets
    while (running && estops < 300) {
      auto done = std::make_shared<std::promise<void>>();
      auto finished = done->get_future();
      safety_->estop(
          inline_post(), [done](bool) { done->set_value(); }, "the stress test's operator");
      if (finished.wait_for(2s) != std::future_status::ready) {
        stop_unanswered = true;
        break;
      }
      safety_->reset_estop("the stress test's operator");
      ++estops;
    }
  });
  std::thread plc_thread([&] {  // feeds both watchdogs once, waits for both to trip, re-arms
    while (running && trip_rounds < 100) {
      safety_->feed_write(0);
      safety_->feed_write(1);
      const bool both_tripped = sms::test::poll_until(
          [&] {
            const SafetyFacts facts = safety_->facts();
            return facts.buses[0].state == WatchdogState::Tripped && facts.buses[1].state == WatchdogState::Tripped;
          },
          2s);
      if (!both_tripped) {
        trip_missed = true;
        break;
      }
      safety_->rearm_watchdogs("the stress test's PLC");
      ++trip_rounds;
    }
  });

  int reads = 0, disagreements = 0, seen_blocked = 0, seen_free = 0, seen_tripped = 0, seen_estop = 0;
  std::string first_disagreement;
  while (std::chrono::steady_clock::now() < until && reads < 200'000) {  // the client
    const DiscreteInputs inputs = discrete_inputs();
    if (inputs.blocked != (inputs.estop || inputs.tripped) || inputs.owed) {
      if (disagreements++ == 0) {
        first_disagreement = "discrete inputs: e-stop " + std::to_string(inputs.estop) + ", tripped " +
                             std::to_string(inputs.tripped) + ", blocked " + std::to_string(inputs.blocked) +
                             ", owed " + std::to_string(inputs.owed);
      }
    }
    (inputs.blocked ? seen_blocked : seen_free) += 1;
    seen_tripped += inputs.tripped ? 1 : 0;
    seen_estop += inputs.estop ? 1 : 0;

    const std::vector<std::uint16_t> registers = input_registers_10_to_119();
    if (registers.size() == 110) {
      const bool latched = registers[0] == 1;
      const bool tripped = registers[110 - 10] == static_cast<std::uint16_t>(WatchdogState::Tripped);
      const bool blocked = registers[118 - 10] == 1;
      if (blocked != (latched || tripped) && disagreements++ == 0) {
        first_disagreement = "input registers: e-stop " + std::to_string(latched) + ", bus 0 tripped " +
                             std::to_string(tripped) + ", bus 0 blocked " + std::to_string(blocked);
      }
    }
    ++reads;
  }
  running = false;
  operator_thread.join();
  plc_thread.join();
  RecordProperty("reads", reads);
  RecordProperty("estops", estops.load());
  RecordProperty("trip_rounds", trip_rounds.load());

  EXPECT_EQ(disagreements, 0) << "of " << reads << " reads; the first: " << first_disagreement;
  EXPECT_FALSE(stop_unanswered) << "an e-stop was not answered within 2 s";
  EXPECT_FALSE(trip_missed) << "a fed watchdog of 10 ms did not trip within 2 s";
  // The threads really interleaved: the client saw every state.
  EXPECT_GT(estops.load(), 20);
  EXPECT_GT(trip_rounds.load(), 5);
  EXPECT_GT(seen_blocked, 0);
  EXPECT_GT(seen_free, 0);
  EXPECT_GT(seen_tripped, 0);
  EXPECT_GT(seen_estop, 0);

  // Quiet again: nothing latched, nothing tripped, nothing blocked, and the gates agree.
  safety_->reset_estop("the stress test's operator");
  safety_->rearm_watchdogs("the stress test's PLC");
  const DiscreteInputs quiet = discrete_inputs();
  EXPECT_FALSE(quiet.estop || quiet.tripped || quiet.blocked || quiet.owed);
  for (const auto& gate : gates_) EXPECT_FALSE(gate->blocked());
}

}  // namespace
}  // namespace sms::gateway
