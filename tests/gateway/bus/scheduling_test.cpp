// The order a bus takes its queued work in (next_level(), bus_engine.h), on queues of stand-in
// jobs with chosen ages: safe stops first, then whatever waited past its age limit (oldest
// first), else strict priority.
#include <gtest/gtest.h>

#include "gateway/bus/bus_engine.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

struct StandIn {
  SteadyClock::time_point queued_at;
};
using Queues = std::array<std::deque<StandIn>, kPriorityCount>;
constexpr std::array<std::chrono::nanoseconds, kPriorityCount> kLimits{0ns, 2ms, 2ms, 10ms};
constexpr auto kSafety = static_cast<std::size_t>(Priority::Safety);
constexpr auto kWrite = static_cast<std::size_t>(Priority::ClientWrite);
constexpr auto kRead = static_cast<std::size_t>(Priority::ClientRead);
constexpr auto kPoll = static_cast<std::size_t>(Priority::Poll);

TEST(Scheduling, NothingQueuedIsNothingToDo) {
  EXPECT_FALSE(next_level(Queues{}, kLimits, SteadyClock::now()));
}

TEST(Scheduling, FreshWorkGoesByPriority) {
  const auto now = SteadyClock::now();
  Queues queues;
  queues[kPoll].push_back({now - 1ms});
  queues[kRead].push_back({now - 1ms});
  queues[kWrite].push_back({now});
  EXPECT_EQ(next_level(queues, kLimits, now), kWrite);
  queues[kWrite].clear();
  EXPECT_EQ(next_level(queues, kLimits, now), kRead);
}

TEST(Scheduling, AReadBehindAFloodOfWritesGoesOnceItWaitedPastItsLimit) {
  const auto now = SteadyClock::now();
  Queues queues;
  queues[kRead].push_back({now - 3ms});
  for (int i = 0; i < 10; ++i) queues[kWrite].push_back({now - 1ms + std::chrono::microseconds(i)});
  EXPECT_EQ(next_level(queues, kLimits, now), kRead);
  // A write queued before the read and overdue too goes first: oldest first, writes in order.
  queues[kWrite].push_front({now - 4ms});
  EXPECT_EQ(next_level(queues, kLimits, now), kWrite);
}

TEST(Scheduling, PollsWaitOnePollPeriodBeforeTheyOvertakeClients) {
  const auto now = SteadyClock::now();
  Queues queues;
  queues[kPoll].push_back({now - 5ms});
  queues[kRead].push_back({now});
  EXPECT_EQ(next_level(queues, kLimits, now), kRead);
  queues[kPoll].front().queued_at = now - 11ms;
  EXPECT_EQ(next_level(queues, kLimits, now), kPoll);
}

TEST(Scheduling, SafeStopsGoFirstWhateverElseWaited) {
  const auto now = SteadyClock::now();
  Queues queues;
  queues[kPoll].push_back({now - 1s});
  queues[kRead].push_back({now - 1s});
  queues[kSafety].push_back({now});
  EXPECT_EQ(next_level(queues, kLimits, now), kSafety);
}

}  // namespace
}  // namespace sms::gateway
