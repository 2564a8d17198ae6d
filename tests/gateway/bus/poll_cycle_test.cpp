// Cyclic polling against the real simulator: one SYNC READ frame per cycle on sts, one READ
// per servo elsewhere, the cache filled from it, a silent servo going offline, being probed
// at the probe period only, and coming back; discovery's summary and identities.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace testing;
using modbus_map::TableId;
using protocol::Bytes;

class PollCycleTest : public ::testing::Test {
 protected:
  void start(std::vector<std::uint8_t> ids, TableId table = TableId::Sts, std::uint32_t baud = 1'000'000,
             std::vector<std::uint8_t> engine_ids = {}) {
    simulator_ = std::make_unique<simulator::SimulatedBus>(simulated_servos(ids, table, baud));
    simulator_->start();
    settings_ = bus_settings(simulator_->slave_path(), engine_ids.empty() ? ids : engine_ids, table, baud);
    tweak(settings_);
    engine_ = make_bus_engine(settings_);
    engine_->start();
    ASSERT_TRUE(eventually([&] { return engine_->discovered(); }));
  }
  virtual void tweak(BusSettings&) {}
  void TearDown() override {
    if (engine_) engine_->stop();
    if (simulator_) simulator_->stop();
  }
  bool all_polled() const {
    for (const auto& servo : settings_.servos) {
      const auto state = engine_->cache().state(servo.servo_id);
      if (!state || !state->has_data) return false;
    }
    return true;
  }
  // Requests the simulator decoded per finished poll cycle over the next `count` cycles (or a
  // few more), with no client traffic: counted cycles, not a time window, whose count a loaded
  // machine would change. Both ends are taken just after a cycle finished, so no cycle is counted
  // by half.
  double requests_per_cycle(std::uint64_t count) {
    const auto after_cycles = [&](std::uint64_t more) {
      const auto cycles = engine_->counters().poll_cycles;
      EXPECT_TRUE(eventually([&] { return engine_->counters().poll_cycles >= cycles + more; }, "poll cycles"));
      return std::pair{simulator_->stats().requests, engine_->counters().poll_cycles};
    };
    const auto [requests_before, cycles_before] = after_cycles(1);
    const auto [requests_after, cycles_after] = after_cycles(count);
    const auto cycles = cycles_after - cycles_before;
    return cycles == 0 ? 0.0 : static_cast<double>(requests_after - requests_before) / static_cast<double>(cycles);
  }

  BusSettings settings_;
  std::unique_ptr<simulator::SimulatedBus> simulator_;
  std::unique_ptr<BusEngine> engine_;
};

TEST_F(PollCycleTest, SyncReadFillsTheCacheOfEveryServoInOneFramePerCycle) {
  start({1, 2, 3, 4, 5, 6});
  ASSERT_TRUE(eventually([&] { return all_polled(); }));
  for (std::uint8_t id = 1; id <= 6; ++id) {
    std::array<std::uint8_t, 2> position{};
    CachedServoState state;
    ASSERT_EQ(engine_->cache().copy(id, 56, position, &state), CacheRead::Ok);
    // Idle servos at their power-on position 2048 = 0x0800, low byte first.
    EXPECT_EQ(position, (std::array<std::uint8_t, 2>{0x00, 0x08})) << "servo " << int(id);
    EXPECT_TRUE(state.online);
    EXPECT_EQ(state.block, (AddressBlock{56, 15}));
  }
  // One SYNC READ frame per cycle: the simulator sees as many requests as there were cycles.
  EXPECT_NEAR(requests_per_cycle(30), 1.0, 0.1);
  // 14 request bytes + 6 x 21 reply bytes at 1 Mbaud is 1.4 ms on the wire, before the servos'
  // return delays: a cycle cannot be shorter.
  EXPECT_GE(engine_->counters().last_poll_cycle_us, 1'400U);
  // A SYNC READ answer a loaded machine hears too late is a timeout, and the servo is then read on
  // its own (the engine's rule), which the bound above allows; what must not happen is a servo
  // lost to it.
  for (std::uint8_t id = 1; id <= 6; ++id) EXPECT_TRUE(engine_->cache().state(id)->online) << "servo " << int(id);
  RecordProperty("timeouts", static_cast<int>(engine_->counters().timeouts));
}

TEST_F(PollCycleTest, CacheFollowsTheServoWhileClientWritesGoFirst) {
  start({1, 2});
  ASSERT_TRUE(eventually([&] { return all_polled(); }));
  // Goal position 2148 = 0x0864 (low byte first): the servo moves there, the polls see it.
  const BusResult write = transact(*engine_, WriteOp{2, 42, {0x64, 0x08}});
  ASSERT_EQ(write.status, BusStatus::Ok) << write.detail;
  std::array<std::uint8_t, 2> position{};
  ASSERT_TRUE(eventually([&] {
    return engine_->cache().copy(2, 56, position) == CacheRead::Ok &&
           position == std::array<std::uint8_t, 2>{0x64, 0x08};
  })) << "cached position "
      << int(position[0]) << "," << int(position[1]);
}

TEST_F(PollCycleTest, Sms1ServosShareOneSyncReadToo) {
  start({1, 2, 3}, TableId::Sms1);
  ASSERT_TRUE(eventually([&] { return all_polled(); }));
  EXPECT_NEAR(requests_per_cycle(30), 1.0, 0.1);
}

TEST_F(PollCycleTest, TablesWithoutSyncReadArePolledOneReadPerServo) {
  start({1, 2, 3}, TableId::D55d, 115'200);
  ASSERT_TRUE(eventually([&] { return all_polled(); }));
  EXPECT_EQ(engine_->cache().state(1)->block, (AddressBlock{36, 14}));
  EXPECT_NEAR(requests_per_cycle(30), 3.0, 0.2);
}

TEST_F(PollCycleTest, SilentServoGoesOfflineLeavesTheSyncReadAndComesBack) {
  LogCapture log;
  start({1, 2, 3});
  ASSERT_TRUE(eventually([&] { return all_polled(); }));

  simulator_->set_offline(3, true);
  ASSERT_TRUE(eventually([&] { return !engine_->cache().state(3)->online; }));
  EXPECT_TRUE(log.contains("bus test: servo 3 offline")) << log.text();
  EXPECT_TRUE(log.contains("probing it every 200 ms")) << log.text();
  EXPECT_TRUE(engine_->cache().state(1)->online);

  // Live access to the offline servo fails at once, without paying timeouts on the bus.
  const auto started = std::chrono::steady_clock::now();
  const BusResult live = transact(*engine_, ReadOp{3, 56, 2}, Priority::ClientRead);
  EXPECT_LT(std::chrono::steady_clock::now() - started, 40ms);
  EXPECT_EQ(live.status, BusStatus::Timeout);
  EXPECT_NE(live.detail.find("servo 3 is offline"), std::string::npos) << live.detail;

  // The others keep being polled: their data stays fresh.
  const auto updated = engine_->cache().state(1)->updated;
  ASSERT_TRUE(eventually([&] { return engine_->cache().state(1)->updated > updated; }));

  simulator_->set_offline(3, false);
  ASSERT_TRUE(eventually([&] { return engine_->cache().state(3)->online; }));
  // The line is logged just after the cache says so, on the bus thread.
  EXPECT_TRUE(eventually([&] { return log.contains("bus test: servo 3 answers again: online"); })) << log.text();
  const BusResult again = transact(*engine_, ReadOp{3, 5, 1}, Priority::ClientRead);
  ASSERT_EQ(again.status, BusStatus::Ok) << again.detail;
  EXPECT_EQ(again.data, (Bytes{0x03}));
}

TEST_F(PollCycleTest, OfflineServoCostsOneTimeoutPerProbePeriodWhileOthersKeepTheirRate) {
  start({1, 2, 3});
  simulator_->set_offline(3, true);
  ASSERT_TRUE(eventually([&] { return !engine_->cache().state(3)->online; }));

  const auto probes_of_3 = [&] { return engine_->cache().state(3)->counters.timeouts; };
  const auto timeouts_before = probes_of_3();
  const auto cycles_before = engine_->counters().poll_cycles;
  const auto retries_before = engine_->counters().retries;
  const auto requests_before = simulator_->stats().requests;
  const auto window_start = std::chrono::steady_clock::now();
  // Five probes as they come, counted: a loaded machine stretches the time they take, not their
  // number.
  ASSERT_TRUE(eventually([&] { return probes_of_3() - timeouts_before >= 5; }, "five probes of servo 3"));
  const auto window = std::chrono::steady_clock::now() - window_start;
  const auto timeouts = probes_of_3() - timeouts_before;
  const auto cycles = engine_->counters().poll_cycles - cycles_before;
  const auto requests = simulator_->stats().requests - requests_before;
  const auto retries = engine_->counters().retries - retries_before;
  // One attempt per probe period (200 ms), not one per cycle: the rule's bound over the window.
  EXPECT_LE(timeouts, static_cast<std::uint64_t>(window / settings_.probe_period) + 1)
      << std::chrono::duration_cast<std::chrono::milliseconds>(window).count() << " ms";
  // Poll period 10 ms: the online servos are polled on between the probes (a probe costs one
  // 50 ms timeout, the probe period is 200 ms).
  EXPECT_GT(cycles, timeouts);
  // Every cycle is still one SYNC READ (servos 1 and 2), plus the probes, plus the attempts a
  // loaded machine made the engine retry (its own count: the product's rule, 1 + retries each).
  EXPECT_LE(requests, cycles + timeouts + retries + 2) << retries << " retries";  // +2: a cycle under way at either end
}

TEST_F(PollCycleTest, DiscoveryLogsOneSummaryAndStoresIdentities) {
  LogCapture log;
  start({1, 2}, TableId::Sts, 1'000'000, {1, 2, 7});
  EXPECT_TRUE(
      log.contains("bus test: " + simulator_->slave_path() + ", feetech at 1000000 bit/s, 2 of 3 servos online"))
      << log.text();
  EXPECT_TRUE(log.contains("servo   1  sts   online   model 10760 (SM40BL) firmware 2.48   status 0x00")) << log.text();
  EXPECT_TRUE(log.contains("servo   7  sts   OFFLINE  no answer to PING (3 attempts)")) << log.text();
  const auto state = engine_->cache().state(2);
  EXPECT_EQ(state->identity.model, 10760);  // 8 / 42 read as one word, low byte first
  EXPECT_EQ(state->identity.firmware, 0x0230);
  EXPECT_FALSE(engine_->cache().state(7)->online);
}

TEST_F(PollCycleTest, DiscoveryLearnsTheResponseLevelAndFollowsClientWritesToIt) {
  start({1, 2});
  EXPECT_EQ(engine_->cache().state(1)->response_level, 1);  // sts factory level
  // Level 0: the servo stops answering writes, so this one is sent without waiting.
  const BusResult write = transact(*engine_, WriteOp{1, 8, {0x00}, false, false});
  ASSERT_EQ(write.status, BusStatus::Ok) << write.detail;
  EXPECT_EQ(engine_->cache().state(1)->response_level, 0);
  EXPECT_EQ(engine_->cache().state(2)->response_level, 1);
  const BusResult level = transact(*engine_, ReadOp{1, 8, 1}, Priority::ClientRead);  // READ is still answered
  ASSERT_EQ(level.status, BusStatus::Ok) << level.detail;
  EXPECT_EQ(level.data, (Bytes{0x00}));
}

TEST_F(PollCycleTest, D55dDiscoveryReadsVendorCodeAndSoftwareVersion) {
  start({3}, TableId::D55d, 115'200);
  const auto state = engine_->cache().state(3);
  EXPECT_TRUE(state->online);
  EXPECT_EQ(state->identity.model, 0x5D);
  EXPECT_EQ(state->identity.firmware, 1);
  EXPECT_EQ(state->response_level, 2);  // d55d factory level: all but broadcasts
}

TEST_F(PollCycleTest, ServoFoundLaterGetsItsIdentityRead) {
  LogCapture log;
  simulator_ = std::make_unique<simulator::SimulatedBus>(simulated_servos({1, 2}));
  simulator_->set_offline(2, true);
  simulator_->start();
  settings_ = bus_settings(simulator_->slave_path(), {1, 2});
  engine_ = make_bus_engine(settings_);
  engine_->start();
  ASSERT_TRUE(eventually([&] { return engine_->discovered(); }));
  EXPECT_TRUE(log.contains("1 of 2 servos online")) << log.text();
  EXPECT_FALSE(engine_->cache().state(2)->identity.model);

  simulator_->set_offline(2, false);
  ASSERT_TRUE(eventually([&] { return engine_->cache().state(2)->identity.model.has_value(); }));
  EXPECT_EQ(engine_->cache().state(2)->identity.model, 10760);
}

}  // namespace
}  // namespace sms::gateway
