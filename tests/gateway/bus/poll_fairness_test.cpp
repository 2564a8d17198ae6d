// Client operations go before polling, but a sustained stream of them must not freeze the
// poll cache or keep an offline servo from its probe: a poll, probe or discovery transaction
// that has waited longer than one poll period (at least 10 ms) goes next.
#include <gtest/gtest.h>

#include <atomic>
#include <memory>
#include <vector>

#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace testing;
using modbus_map::TableId;

// Keeps `depth` live client READs queued on the engine until stopped: each completion submits
// the next one, so the client queue is never empty.
class ClientFlood {
 public:
  ClientFlood(BusEngine& engine, std::uint8_t servo_id, unsigned depth) : engine_(engine), servo_id_(servo_id) {
    for (unsigned i = 0; i < depth; ++i) submit_next();
  }
  ~ClientFlood() { stop(); }
  ClientFlood(const ClientFlood&) = delete;
  ClientFlood& operator=(const ClientFlood&) = delete;

  void stop() {
    running_->store(false);
    // In-flight READs finish within a few transactions; their completions do not resubmit.
    eventually([&] { return *outstanding_ == 0; });
  }
  std::uint64_t answered() const { return answered_->load(); }

 private:
  void submit_next() {
    ++*outstanding_;
    engine_.submit(ReadOp{servo_id_, 56, 2}, Priority::ClientRead,
                   [this, running = running_, outstanding = outstanding_, answered = answered_](BusResult result) {
                     if (result.status == BusStatus::Ok) ++*answered;
                     // Not from a refusal completion: those run inside submit() itself.
                     const bool again = running->load() && result.status == BusStatus::Ok;
                     if (again) submit_next();
                     --*outstanding;
                   });
  }

  BusEngine& engine_;
  std::uint8_t servo_id_;
  std::shared_ptr<std::atomic<bool>> running_ = std::make_shared<std::atomic<bool>>(true);
  std::shared_ptr<std::atomic<int>> outstanding_ = std::make_shared<std::atomic<int>>(0);
  std::shared_ptr<std::atomic<std::uint64_t>> answered_ = std::make_shared<std::atomic<std::uint64_t>>(0);
};

class PollFairnessTest : public ::testing::Test {
 protected:
  void start(std::vector<std::uint8_t> ids) {
    simulator_ = std::make_unique<simulator::SimulatedBus>(simulated_servos(ids));
    simulator_->start();
    settings_ = bus_settings(simulator_->slave_path(), ids);
    engine_ = make_bus_engine(settings_);
    engine_->start();
    ASSERT_TRUE(eventually([&] { return engine_->discovered(); }));
    ASSERT_TRUE(eventually([&] { return engine_->counters().poll_cycles > 0; }));
  }
  void TearDown() override {
    flood_.reset();
    if (engine_) engine_->stop();
    if (simulator_) simulator_->stop();
  }

  BusSettings settings_;
  std::unique_ptr<simulator::SimulatedBus> simulator_;
  std::unique_ptr<BusEngine> engine_;
  std::unique_ptr<ClientFlood> flood_;
};

TEST_F(PollFairnessTest, PollCyclesContinueWhileClientReadsKeepTheQueueFull) {
  start({1, 2});
  flood_ = std::make_unique<ClientFlood>(*engine_, 1, 4);
  ASSERT_TRUE(eventually([&] { return flood_->answered() > 20; }));

  const auto cycles_before = engine_->counters().poll_cycles;
  const auto answered_before = flood_->answered();
  // Poll period 10 ms: a cycle waits at most about one period behind the clients; without the
  // rule the queue never empties and no cycle runs. Counted, not timed: a loaded machine only
  // makes the cycles come later.
  ASSERT_TRUE(eventually([&] { return engine_->counters().poll_cycles - cycles_before >= 10; },
                         "10 poll cycles while the clients keep the queue full"));
  const auto cycles = engine_->counters().poll_cycles - cycles_before;
  const auto answered = flood_->answered() - answered_before;
  // The clients are not starved either: a cycle's work goes after the work queued before it, and
  // the flood keeps 4 reads in the engine (3 queued while one is on the wire), so at least 3
  // client answers come between two cycles. By the rule, not by how many reads fit in a poll
  // period: that is wall-clock time (more than 5 a cycle failed at a load of 12, where each
  // transaction took longer and the 10 ms period came sooner).
  EXPECT_GE(answered, 3 * (cycles - 1));
  // The cache of the servo no client reads is fresh: it was polled within the last cycles.
  const auto age = engine_->cache().state(2)->age(std::chrono::steady_clock::now());
  ASSERT_TRUE(age.has_value());
  EXPECT_LT(*age, 1s);
}

TEST_F(PollFairnessTest, OfflineServoIsProbedAndComesBackWhileClientsKeepTheQueueFull) {
  start({1, 2, 3});
  simulator_->set_offline(3, true);
  ASSERT_TRUE(eventually([&] { return !engine_->cache().state(3)->online; }));

  flood_ = std::make_unique<ClientFlood>(*engine_, 1, 4);
  ASSERT_TRUE(eventually([&] { return flood_->answered() > 20; }));
  simulator_->set_offline(3, false);
  // Probe period 200 ms: the next probe, queued behind the clients, still goes out.
  EXPECT_TRUE(eventually([&] { return engine_->cache().state(3)->online; }));
  EXPECT_GT(flood_->answered(), 20U);
}

}  // namespace
}  // namespace sms::gateway
