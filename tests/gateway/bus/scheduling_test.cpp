// The bus queue's rules (JobQueue, job_queue.h) on stand-in jobs, without a bus: the order it
// takes its work in — safe stops first, then whatever waited past its age limit (oldest first),
// else strict priority — looked at from chosen moments after the jobs were queued, and its
// admission: QueueFull at the depth (never for a safe stop), Cancelled and BusDown, each answered
// at once on the caller's thread.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "gateway/bus/job_queue.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

struct StandIn {
  explicit StandIn(std::string n) : name(std::move(n)) {}
  std::string name;
  bool client = false;
  SteadyClock::time_point queued_at{};
  Completion done;
};

class Scheduling : public ::testing::Test {
 protected:
  static BusSettings settings() {
    BusSettings settings;
    settings.name = "arm";
    settings.serial.device = "/dev/ttyUSB0";
    settings.poll_period = 10ms;  // the engine's own work may wait 10 ms, client work 2 ms
    settings.queue_depth = 3;
    return settings;
  }
  void SetUp() override {
    ASSERT_TRUE(queue_.open());
    queue_.line_up();
  }

  // Queues a client job; the refusal it got at once, or "queued".
  std::string submit(const std::string& name, Priority priority) {
    std::string answer = "queued";
    StandIn job{name};
    job.done = [&answer](BusResult result) { answer = std::string(to_string(result.status)) + ": " + result.detail; };
    queue_.submit(std::move(job), priority);
    return answer;
  }
  void poll(const std::string& name) { queue_.push_internal(StandIn{name}); }
  // What the queue takes at `at`, one after another, until it is empty.
  std::vector<std::string> taken(SteadyClock::time_point at) {
    std::vector<std::string> names;
    while (auto job = queue_.take(at)) names.push_back(job->name);
    return names;
  }
  std::string next(SteadyClock::time_point at) {
    auto job = queue_.take(at);
    return job ? job->name : "nothing";
  }

  const BusSettings settings_ = settings();
  BusCounters counters_;
  JobQueue<StandIn> queue_{settings_, counters_};
};

using Names = std::vector<std::string>;

TEST_F(Scheduling, NothingQueuedIsNothingToDo) { EXPECT_EQ(next(SteadyClock::now()), "nothing"); }

TEST_F(Scheduling, FreshWorkGoesByPriorityFifoWithinOne) {
  const auto before = SteadyClock::now();  // looked at from then: nothing has waited
  poll("poll");
  submit("read", Priority::ClientRead);
  submit("write 1", Priority::ClientWrite);
  submit("write 2", Priority::ClientWrite);
  EXPECT_EQ(taken(before), (Names{"write 1", "write 2", "read", "poll"}));
}

TEST_F(Scheduling, OverdueWorkGoesOldestFirstSoAReadBehindAFloodOfWritesIsNotStarved) {
  submit("write 1", Priority::ClientWrite);
  submit("read", Priority::ClientRead);
  submit("write 2", Priority::ClientWrite);
  // Fresh, they would go by priority (the read behind both writes); 3 ms later every one is past
  // its 2 ms: oldest first, each priority still in order.
  EXPECT_EQ(taken(SteadyClock::now() + 3ms), (Names{"write 1", "read", "write 2"}));
}

TEST_F(Scheduling, PollsWaitOnePollPeriodBeforeTheyOvertakeClients) {
  const auto queued = SteadyClock::now();
  poll("poll");
  submit("read 1", Priority::ClientRead);
  EXPECT_EQ(next(queued + 5ms), "read 1");  // the poll is not yet past its 10 ms
  submit("read 2", Priority::ClientRead);
  EXPECT_EQ(next(queued + 15ms), "poll");  // now it is, and older than the read
  EXPECT_EQ(next(queued + 15ms), "read 2");
}

TEST_F(Scheduling, SafeStopsGoFirstWhateverElseWaited) {
  poll("poll");
  submit("read", Priority::ClientRead);
  submit("stop", Priority::Safety);
  EXPECT_EQ(next(SteadyClock::now() + 1s), "stop");
}

TEST_F(Scheduling, AFullQueueRefusesClientWorkAtOnceButNeverASafeStop) {
  for (const char* name : {"a", "b", "c"}) EXPECT_EQ(submit(name, Priority::ClientRead), "queued");
  poll("poll");  // the engine's own work does not count against the depth
  EXPECT_EQ(submit("d", Priority::ClientWrite), "queue full: bus arm: 3 operations already queued");
  EXPECT_EQ(counters_.queue_full.load(), 1u);
  EXPECT_EQ(submit("stop", Priority::Safety), "queued");
  EXPECT_EQ(next(SteadyClock::now()), "stop");
  EXPECT_EQ(next(SteadyClock::now()), "a");  // a slot is free again
  EXPECT_EQ(submit("e", Priority::ClientWrite), "queued");
}

TEST_F(Scheduling, ALineThatGoesDownHandsBackTheClientJobsAndRefusesMore) {
  submit("read", Priority::ClientRead);
  poll("poll");
  const auto clients = queue_.line_down();
  ASSERT_EQ(clients.size(), 1u);  // the engine's own work is dropped, rebuilt when the bus is back
  EXPECT_EQ(clients[0].name, "read");
  EXPECT_FALSE(queue_.line_is_up());
  EXPECT_EQ(submit("write", Priority::ClientWrite),
            "bus down: bus arm: serial port /dev/ttyUSB0 is not open (bus down)");
  EXPECT_EQ(next(SteadyClock::now()), "nothing");
  queue_.line_up();
  EXPECT_EQ(submit("write", Priority::ClientWrite), "queued");
}

TEST_F(Scheduling, AClosedQueueRefusesEverythingAsCancelled) {
  EXPECT_FALSE(queue_.open());  // already open
  queue_.close();
  EXPECT_TRUE(queue_.closing());
  EXPECT_EQ(submit("stop", Priority::Safety), "cancelled: bus arm: the bus engine is not running");
}

TEST_F(Scheduling, AThrowingCompletionIsContained) {
  StandIn job{"x"};
  job.done = [](BusResult) { throw std::runtime_error("handler bug"); };
  EXPECT_NO_THROW(queue_.complete(job, BusResult{}));
}

}  // namespace
}  // namespace sms::gateway
