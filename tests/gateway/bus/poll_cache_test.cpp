// PollCache: what the Modbus TCP threads read, and PollScheduler: what a poll cycle sends.
#include "gateway/bus/poll_cache.h"

#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <thread>
#include <vector>

#include "gateway/bus/poll_scheduler.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

std::vector<PollCache::ServoEntry> two_servos() { return {{1, {56, 4}}, {9, {36, 2}}}; }

TEST(PollCache, CopiesBytesOfTheBlockAtTheirAddresses) {
  PollCache cache(two_servos());
  const auto when = SteadyClock::now();
  cache.store_block(1, std::vector<std::uint8_t>{0x11, 0x22, 0x33, 0x44}, when);
  std::array<std::uint8_t, 2> middle{};
  CachedServoState state;
  ASSERT_EQ(cache.copy(1, 57, middle, &state), CacheRead::Ok);
  EXPECT_EQ(middle, (std::array<std::uint8_t, 2>{0x22, 0x33}));
  EXPECT_TRUE(state.online);
  EXPECT_TRUE(state.has_data);
  EXPECT_EQ(state.updated, when);
  EXPECT_EQ(state.age(when + 250ms), std::optional<SteadyClock::duration>(250ms));
}

TEST(PollCache, RangesOutsideTheBlockAndUnknownServosAreSaidSo) {
  PollCache cache(two_servos());
  cache.store_block(1, std::vector<std::uint8_t>{1, 2, 3, 4}, SteadyClock::now());
  std::array<std::uint8_t, 2> out{};
  EXPECT_EQ(cache.copy(1, 55, out), CacheRead::OutsideBlock);  // starts before
  EXPECT_EQ(cache.copy(1, 59, out), CacheRead::OutsideBlock);  // runs past the end
  EXPECT_EQ(cache.copy(2, 56, out), CacheRead::UnknownServo);
  EXPECT_FALSE(cache.contains(2));
  EXPECT_FALSE(cache.state(2));
}

TEST(PollCache, NeverPolledServoHasNoDataButReportsItsState) {
  PollCache cache(two_servos());
  std::array<std::uint8_t, 2> out{0xAA, 0xAA};
  CachedServoState state;
  EXPECT_EQ(cache.copy(9, 36, out, &state), CacheRead::NoData);
  EXPECT_EQ(out, (std::array<std::uint8_t, 2>{0xAA, 0xAA}));
  EXPECT_FALSE(state.online);
  EXPECT_FALSE(state.has_data);
  EXPECT_FALSE(state.age(SteadyClock::now()));
}

TEST(PollCache, OfflineServoKeepsItsLastDataAndItsAgeGrows) {
  PollCache cache(two_servos());
  const auto when = SteadyClock::now();
  cache.store_block(9, std::vector<std::uint8_t>{0x05, 0x06}, when);
  cache.set_online(9, false);
  std::array<std::uint8_t, 2> out{};
  CachedServoState state;
  ASSERT_EQ(cache.copy(9, 36, out, &state), CacheRead::Ok);
  EXPECT_EQ(out, (std::array<std::uint8_t, 2>{0x05, 0x06}));
  EXPECT_FALSE(state.online);
  EXPECT_EQ(state.age(when + 3s), std::optional<SteadyClock::duration>(3s));
  EXPECT_EQ(cache.online_count(), 0U);
}

// Why a servo is offline: a servo known to answer late stays "answers late" through its
// unanswered probes, and an answer clears the reason.
TEST(PollCache, AServoOfflineForAnsweringLateKeepsThatReasonUntilItAnswers) {
  PollCache cache(two_servos());
  cache.set_online(9, true);
  EXPECT_EQ(cache.state(9)->offline_reason, OfflineReason::None);
  EXPECT_EQ(cache.set_offline(9, OfflineReason::AnswersLate), OfflineReason::None);
  EXPECT_EQ(cache.set_offline(9, OfflineReason::NoAnswer), OfflineReason::AnswersLate);  // a probe unanswered
  EXPECT_EQ(cache.state(9)->offline_reason, OfflineReason::AnswersLate);
  EXPECT_FALSE(cache.state(9)->online);
  EXPECT_EQ(cache.offline_count(OfflineReason::AnswersLate), 1U);
  cache.store_block(9, std::vector<std::uint8_t>{0x01, 0x02}, SteadyClock::now());
  EXPECT_TRUE(cache.state(9)->online);
  EXPECT_EQ(cache.state(9)->offline_reason, OfflineReason::None);
  // A silent servo first, then its late answers come: the reason becomes "answers late".
  cache.set_online(9, false);
  EXPECT_EQ(cache.state(9)->offline_reason, OfflineReason::NoAnswer);
  cache.set_offline(9, OfflineReason::AnswersLate);
  EXPECT_EQ(cache.state(9)->offline_reason, OfflineReason::AnswersLate);
}

TEST(PollCache, BlockOfTheWrongSizeIsNotStored) {
  PollCache cache(two_servos());
  cache.store_block(1, std::vector<std::uint8_t>{1, 2, 3}, SteadyClock::now());
  std::array<std::uint8_t, 1> out{};
  EXPECT_EQ(cache.copy(1, 56, out), CacheRead::NoData);
}

TEST(PollCache, CountersAndIdentityArePerServo) {
  PollCache cache(two_servos());
  cache.counters(9)->replies_ok += 7;
  cache.counters(9)->timeouts += 2;
  cache.counters(9)->last_status = 0x24;
  cache.set_identity(9, ServoIdentity{0x5D, 1});
  const auto state = cache.state(9);
  EXPECT_EQ(state->counters.replies_ok, 7U);
  EXPECT_EQ(state->counters.timeouts, 2U);
  EXPECT_EQ(state->counters.last_status, 0x24);
  EXPECT_EQ(state->identity, (ServoIdentity{0x5D, 1}));
  EXPECT_EQ(cache.state(1)->counters.replies_ok, 0U);
  EXPECT_EQ(cache.counters(3), nullptr);
}

TEST(PollCache, RegisterBlocksHoldTwoBytesPerAddress) {
  // An SMSMB servo's feedback registers 0x100-0x107, each high byte first as on the wire.
  PollCache cache(std::vector<PollCache::ServoEntry>{{5, {0x100, 8}}}, 2);
  EXPECT_EQ(cache.bytes_per_address(), 2);
  const std::vector<std::uint8_t> registers{0x00, 0x00, 0x08, 0x00, 0x00, 0x10, 0x00, 0x00,
                                            0x00, 0x78, 0x00, 0x1C, 0x00, 0x00, 0x00, 0x03};
  cache.store_block(5, registers, SteadyClock::now());
  std::array<std::uint8_t, 4> position_and_speed{};
  ASSERT_EQ(cache.copy(5, 0x101, position_and_speed), CacheRead::Ok);
  EXPECT_EQ(position_and_speed, (std::array<std::uint8_t, 4>{0x08, 0x00, 0x00, 0x10}));
  std::array<std::uint8_t, 3> half_a_register{};
  EXPECT_EQ(cache.copy(5, 0x101, half_a_register), CacheRead::OutsideBlock);
  std::array<std::uint8_t, 4> past_the_end{};
  EXPECT_EQ(cache.copy(5, 0x107, past_the_end), CacheRead::OutsideBlock);
  std::array<std::uint8_t, 2> current{};
  ASSERT_EQ(cache.copy(5, 0x107, current), CacheRead::Ok);
  EXPECT_EQ(current, (std::array<std::uint8_t, 2>{0x00, 0x03}));
  // A block of one byte per register is not what this cache holds.
  PollCache fresh(std::vector<PollCache::ServoEntry>{{5, {0x100, 8}}}, 2);
  fresh.store_block(5, std::vector<std::uint8_t>(8, 0), SteadyClock::now());
  EXPECT_EQ(fresh.copy(5, 0x100, current), CacheRead::NoData);
  EXPECT_THROW(PollCache(std::vector<PollCache::ServoEntry>{{5, {0x100, 8}}}, 3), std::invalid_argument);
}

TEST(PollCache, ResponseLevelIsUnknownUntilSet) {
  PollCache cache(two_servos());
  EXPECT_FALSE(cache.state(1)->response_level);
  cache.set_response_level(1, 0);
  EXPECT_EQ(cache.state(1)->response_level, 0);
}

TEST(PollCache, DuplicateOrBroadcastIdsAreRejected) {
  EXPECT_THROW(PollCache(std::vector<PollCache::ServoEntry>{{1, {0, 1}}, {1, {0, 1}}}), std::invalid_argument);
  EXPECT_THROW(PollCache(std::vector<PollCache::ServoEntry>{{254, {0, 1}}}), std::invalid_argument);
}

TEST(PollCache, ReadersSeeWholeBlocksWhileTheBusThreadWrites) {
  PollCache cache(std::vector<PollCache::ServoEntry>{{1, {56, 8}}});
  std::atomic<bool> stop{false};
  std::thread writer([&] {
    for (std::uint8_t value = 0; !stop.load(); ++value) {
      cache.store_block(1, std::vector<std::uint8_t>(8, value), SteadyClock::now());
    }
  });
  for (int i = 0; i < 20'000; ++i) {
    std::array<std::uint8_t, 8> out{};
    if (cache.copy(1, 56, out) != CacheRead::Ok) continue;
    for (const auto byte : out) ASSERT_EQ(byte, out[0]) << "a torn block";
  }
  stop = true;
  writer.join();
}

// --- PollScheduler --------------------------------------------------------------------------------

std::vector<PollTarget> mixed_bus() {
  return {{1, {56, 15}, true}, {2, {56, 15}, true}, {3, {56, 15}, true}, {4, {56, 15}, false}};
}

TEST(PollScheduler, SyncReadCapableServosShareOneFrameOthersGetAReadEach) {
  PollScheduler scheduler(mixed_bus(), 1000ms);
  const auto plan = scheduler.plan_cycle(SteadyClock::now());
  ASSERT_EQ(plan.sync_reads.size(), 1U);
  EXPECT_EQ(plan.sync_reads[0].block, (AddressBlock{56, 15}));
  EXPECT_EQ(plan.sync_reads[0].ids, (std::vector<std::uint8_t>{1, 2, 3}));
  EXPECT_EQ(plan.reads, (std::vector<std::uint8_t>{4}));
  EXPECT_TRUE(plan.probes.empty());
}

TEST(PollScheduler, ServosPollingDifferentBlocksGetDifferentSyncReads) {
  PollScheduler scheduler({{1, {56, 15}, true}, {2, {56, 15}, true}, {3, {56, 8}, true}, {4, {56, 8}, true}}, 1000ms);
  const auto plan = scheduler.plan_cycle(SteadyClock::now());
  ASSERT_EQ(plan.sync_reads.size(), 2U);
  EXPECT_EQ(plan.sync_reads[0].ids, (std::vector<std::uint8_t>{1, 2}));
  EXPECT_EQ(plan.sync_reads[1].ids, (std::vector<std::uint8_t>{3, 4}));
}

TEST(PollScheduler, OfflineServoLeavesTheSyncReadAndIsProbedOncePerPeriod) {
  PollScheduler scheduler(mixed_bus(), 1000ms);
  const auto t0 = SteadyClock::now();
  EXPECT_EQ(scheduler.silent(2, t0), PresenceChange::WentOffline);
  EXPECT_EQ(scheduler.silent(2, t0), PresenceChange::None);  // already offline

  const auto soon = scheduler.plan_cycle(t0 + 10ms);
  ASSERT_EQ(soon.sync_reads.size(), 1U);
  EXPECT_EQ(soon.sync_reads[0].ids, (std::vector<std::uint8_t>{1, 3}));
  EXPECT_TRUE(soon.probes.empty());
  EXPECT_EQ(scheduler.next_probe_due(), t0 + 1000ms);

  const auto due = scheduler.plan_cycle(t0 + 1000ms);
  EXPECT_EQ(due.probes, (std::vector<std::uint8_t>{2}));
  // The probe failed at t0 + 1.05 s: the next one is a whole period later.
  scheduler.silent(2, t0 + 1050ms);
  EXPECT_TRUE(scheduler.plan_cycle(t0 + 2000ms).probes.empty());
  EXPECT_EQ(scheduler.plan_cycle(t0 + 2050ms).probes, (std::vector<std::uint8_t>{2}));

  EXPECT_EQ(scheduler.answered(2), PresenceChange::CameOnline);
  EXPECT_EQ(scheduler.plan_cycle(t0 + 2100ms).sync_reads[0].ids, (std::vector<std::uint8_t>{1, 2, 3}));
  EXPECT_FALSE(scheduler.next_probe_due());
}

TEST(PollScheduler, ALoneSyncReadServoIsReadWithAPlainRead) {
  PollScheduler scheduler(mixed_bus(), 1000ms);
  const auto now = SteadyClock::now();
  scheduler.silent(1, now);
  scheduler.silent(2, now);
  const auto plan = scheduler.plan_cycle(now);
  EXPECT_TRUE(plan.sync_reads.empty());
  EXPECT_EQ(plan.reads, (std::vector<std::uint8_t>{4, 3}));
}

TEST(PollScheduler, ForgettingEveryoneMakesThemPolledAgain) {
  PollScheduler scheduler(mixed_bus(), 1000ms);
  scheduler.silent(1, SteadyClock::now());
  scheduler.forget_all();
  EXPECT_EQ(scheduler.presence(1), Presence::Unknown);
  EXPECT_EQ(scheduler.plan_cycle(SteadyClock::now()).sync_reads[0].ids, (std::vector<std::uint8_t>{1, 2, 3}));
}

}  // namespace
}  // namespace sms::gateway
