// The console's login backoff and its password-check worker (login_guard.h): the waits on a
// stepped clock, the memory bound, and the worker's queue with a check that blocks until the
// test lets it go.
#include "gateway/console/login_guard.h"

#include <gtest/gtest.h>

#include <condition_variable>
#include <future>
#include <mutex>
#include <thread>

namespace sms::gateway::console {
namespace {

using namespace std::chrono_literals;
using Clock = LoginBackoff::Clock;
using Result = LoginOutcome::Result;

const Clock::time_point kStart = Clock::time_point{} + 1000h;

TEST(LoginBackoff, FiveFailuresAreFreeThenEachDoublesTheWait) {
  LoginBackoff backoff({"alice"});
  for (int i = 0; i < 4; ++i) {
    backoff.count_attempt("10.0.0.7", "mallory", kStart);
    EXPECT_FALSE(backoff.throttled("10.0.0.7", "mallory", kStart)) << "after failure " << i + 1;
  }
  backoff.count_attempt("10.0.0.7", "mallory", kStart);
  auto wait = backoff.throttled("10.0.0.7", "someone-else", kStart);
  ASSERT_TRUE(wait);
  EXPECT_EQ(wait->retry_after, 1s);
  EXPECT_EQ(wait->why, "too many failed logins from 10.0.0.7");
  EXPECT_EQ(backoff.throttled("10.0.0.7", "mallory", kStart + 500ms)->retry_after, 1s);  // rounded up
  EXPECT_FALSE(backoff.throttled("10.0.0.7", "mallory", kStart + 1s));
  EXPECT_FALSE(backoff.throttled("10.0.0.8", "alice", kStart)) << "another address, another user";

  Clock::time_point now = kStart + 1s;
  std::chrono::seconds expected{2};
  for (int failure = 6; failure <= 16; ++failure) {
    backoff.count_attempt("10.0.0.7", "mallory", now);
    wait = backoff.throttled("10.0.0.7", "anyone", now);
    ASSERT_TRUE(wait) << "failure " << failure;
    EXPECT_EQ(wait->retry_after, std::min<std::chrono::seconds>(expected, 300s)) << "failure " << failure;
    now += wait->retry_after;
    expected *= 2;
  }
  EXPECT_EQ(backoff.addresses_waiting(now - 1s), 1u);
  EXPECT_EQ(backoff.addresses_waiting(now), 0u);
}

TEST(LoginBackoff, AUserWaitsWhateverAddressTheFailuresCameFrom) {
  LoginBackoff backoff({"alice", "bob"});
  for (int i = 1; i <= 5; ++i) backoff.count_attempt("10.0.1." + std::to_string(i), "alice", kStart);
  const auto wait = backoff.throttled("10.0.2.1", "alice", kStart);
  ASSERT_TRUE(wait);
  EXPECT_EQ(wait->retry_after, 1s);
  EXPECT_EQ(wait->why, "too many failed logins for user `alice`");
  EXPECT_FALSE(backoff.throttled("10.0.2.1", "bob", kStart));
  EXPECT_EQ(backoff.users_waiting(kStart), 1u);
  EXPECT_EQ(backoff.addresses_waiting(kStart), 0u);
  // A user's wait stops at a minute (anyone may fail in their name); an address's goes on.
  Clock::time_point now = kStart;
  for (int i = 0; i < 20; ++i) backoff.count_attempt("10.0.3." + std::to_string(i), "alice", now);
  EXPECT_EQ(backoff.throttled("10.0.4.1", "alice", now)->retry_after, 60s);
  // Names that are not users wait the same way: the answers tell no name apart.
  for (int i = 1; i <= 5; ++i) backoff.count_attempt("10.0.5." + std::to_string(i), "root", kStart);
  EXPECT_EQ(backoff.throttled("10.0.6.1", "root", kStart)->why, "too many failed logins for user `root`");
}

TEST(LoginBackoff, ASuccessClearsTheUsersCountAndTakesItsAttemptBackFromTheAddress) {
  LoginBackoff backoff({"alice"});
  for (int i = 0; i < 4; ++i) backoff.count_attempt("10.0.0.7", "alice", kStart);
  // The fifth, a second later: counted until its check says otherwise.
  const auto attempt = backoff.count_attempt("10.0.0.7", "alice", kStart + 1s);
  ASSERT_TRUE(backoff.throttled("10.0.0.7", "alice", kStart + 1s));
  backoff.succeeded("10.0.0.7", "alice", attempt);
  EXPECT_FALSE(backoff.throttled("10.0.0.7", "alice", kStart + 1s));
  EXPECT_EQ(backoff.users_waiting(kStart + 1s), 0u);
  // The address keeps its four failures: one more and it waits; the user's count starts again at 1.
  backoff.count_attempt("10.0.0.7", "alice", kStart + 2s);
  EXPECT_EQ(backoff.throttled("10.0.0.7", "alice", kStart + 2s)->why, "too many failed logins from 10.0.0.7");
  EXPECT_FALSE(backoff.throttled("10.0.0.8", "alice", kStart + 2s));
}

TEST(LoginBackoff, ASuccessAfterTheWaitLeavesTheAddressFree) {
  LoginBackoff backoff({"alice"});
  for (int i = 0; i < 5; ++i) backoff.count_attempt("10.0.0.7", "mallory", kStart);
  ASSERT_TRUE(backoff.throttled("10.0.0.7", "alice", kStart));
  const auto attempt = backoff.count_attempt("10.0.0.7", "alice", kStart + 1s);
  backoff.succeeded("10.0.0.7", "alice", attempt);
  // Its wait is the one the five failures made (over), not a new one from the success.
  EXPECT_FALSE(backoff.throttled("10.0.0.7", "alice", kStart + 1s));
}

TEST(LoginBackoff, CountsAreForgottenAfterAQuietQuarterOfAnHour) {
  LoginBackoff backoff({});
  for (int i = 0; i < 5; ++i) backoff.count_attempt("10.0.0.7", "x", kStart);
  backoff.count_attempt("10.0.0.7", "x", kStart + 1s + 15min);  // wait ended at +1 s; forgotten 15 min later
  EXPECT_FALSE(backoff.throttled("10.0.0.7", "x", kStart + 1s + 15min));
}

TEST(LoginBackoff, MemoryIsBoundedAndTheConfiguredUsersAreKept) {
  BackoffLimits limits;
  limits.max_addresses = 8;
  limits.max_unknown_names = 4;
  LoginBackoff backoff({"alice"}, limits);
  for (int i = 0; i < 5; ++i) backoff.count_attempt("10.1.0.1", "alice", kStart);
  Clock::time_point now = kStart;
  for (int i = 0; i < 1000; ++i) {
    now += 100us;  // all within alice's first wait
    backoff.count_attempt("10.2." + std::to_string(i / 250) + "." + std::to_string(i % 250), "n" + std::to_string(i),
                          now);
  }
  EXPECT_LE(backoff.tracked(), 8u + 4u + 1u);
  EXPECT_TRUE(backoff.throttled("10.3.0.1", "alice", now)) << "a flood of names does not make alice's count go";
  EXPECT_FALSE(backoff.throttled("10.1.0.1", "bob", now)) << "the oldest address made room";
}

TEST(LoginBackoff, AnIpv6HostIsCountedByItsSlash64) {
  EXPECT_EQ(LoginBackoff::address_key("10.0.0.1"), "10.0.0.1");
  EXPECT_EQ(LoginBackoff::address_key("2001:db8:1:2:aaaa::1"), "2001:db8:1:2::/64");
  EXPECT_EQ(LoginBackoff::address_key("2001:db8:1:2:bbbb::9"), "2001:db8:1:2::/64");
  EXPECT_EQ(LoginBackoff::address_key("::ffff:192.168.10.7"), "192.168.10.7");
}

// What the console thread would run: the work `post` hands over, run when the test pumps it.
class ConsoleThread {
 public:
  LoginGuard::Post post() {
    return [this](std::function<void()> work) {
      std::lock_guard lock(mutex_);
      posted_.push_back(std::move(work));
      arrived_.notify_all();
    };
  }
  // Runs `count` posted jobs, waiting up to 10 s for each.
  void pump(std::size_t count) {
    for (std::size_t i = 0; i < count; ++i) {
      std::function<void()> work;
      {
        std::unique_lock lock(mutex_);
        ASSERT_TRUE(arrived_.wait_for(lock, 10s, [this] { return !posted_.empty(); })) << "nothing was posted";
        work = std::move(posted_.front());
        posted_.pop_front();
      }
      work();
    }
  }
  std::size_t waiting() {
    std::lock_guard lock(mutex_);
    return posted_.size();
  }

 private:
  std::mutex mutex_;
  std::condition_variable arrived_;
  std::deque<std::function<void()>> posted_;
};

config::ConsoleConfig console_with(std::string name) {
  config::ConsoleConfig console;
  console.users.push_back({std::move(name), config::Role::Operate, "$argon2id$unused"});
  return console;
}

TEST(LoginGuard, ChecksOnItsWorkerAndAnswersThroughTheConsoleThread) {
  ConsoleThread console;
  std::thread::id checked_on;
  LoginGuard guard(console_with("alice"), console.post(), {},
                   [&](std::string_view user, std::string_view password) -> std::optional<Principal> {
                     checked_on = std::this_thread::get_id();
                     if (user == "alice" && password == "right")
                       return Principal{"alice", config::Role::Operate, "password"};
                     return std::nullopt;
                   });
  std::vector<LoginOutcome> outcomes;
  guard.login("127.0.0.1", "alice", "right", [&](LoginOutcome outcome) { outcomes.push_back(std::move(outcome)); });
  EXPECT_TRUE(outcomes.empty()) << "answered on the caller's thread";
  console.pump(1);
  ASSERT_EQ(outcomes.size(), 1u);
  EXPECT_EQ(outcomes[0].result, Result::Ok);
  EXPECT_EQ(outcomes[0].who->name, "alice");
  EXPECT_NE(checked_on, std::this_thread::get_id());
  guard.login("127.0.0.1", "alice", "wrong", [&](LoginOutcome outcome) { outcomes.push_back(std::move(outcome)); });
  console.pump(1);
  EXPECT_EQ(outcomes[1].result, Result::Failed);
  EXPECT_EQ(outcomes[1].message, "unknown user or wrong password");
  const LoginStats stats = guard.stats();
  EXPECT_EQ(stats.ok, 1u);
  EXPECT_EQ(stats.failed, 1u);
}

TEST(LoginGuard, AFullQueueIsRefusedAtOnce) {
  ConsoleThread console;
  std::promise<void> entered;
  std::promise<void> release;
  std::shared_future<void> released = release.get_future().share();
  bool first = true;
  LoginGuardLimits limits;
  limits.queue_depth = 4;
  LoginGuard guard(console_with("alice"), console.post(), limits,
                   [&](std::string_view, std::string_view) -> std::optional<Principal> {
                     if (first) {
                       first = false;
                       entered.set_value();
                       released.wait();
                     }
                     return std::nullopt;
                   });
  std::vector<Result> results;
  const auto record = [&](LoginOutcome outcome) { results.push_back(outcome.result); };
  guard.login("10.0.0.1", "u1", "x", record);
  ASSERT_EQ(entered.get_future().wait_for(10s), std::future_status::ready) << "the worker never took the login";
  for (int i = 2; i <= 5; ++i) guard.login("10.0.0." + std::to_string(i), "u" + std::to_string(i), "x", record);
  ASSERT_TRUE(results.empty());
  std::optional<LoginOutcome> refused;
  guard.login("10.0.0.6", "u6", "x", [&](LoginOutcome outcome) { refused = std::move(outcome); });
  ASSERT_TRUE(refused) << "a login past the queue waits for nothing";
  EXPECT_EQ(refused->result, Result::Busy);
  EXPECT_EQ(refused->retry_after, 1s);
  EXPECT_EQ(refused->message, "the console is busy checking other logins: try again in 1 s");
  release.set_value();
  console.pump(5);
  EXPECT_EQ(results, std::vector<Result>(5, Result::Failed));
  EXPECT_EQ(guard.stats().busy, 1u);
  EXPECT_EQ(guard.stats().failed, 5u);
}

TEST(LoginGuard, AWaitingAddressIsAnsweredAtOnceWithoutACheck) {
  ConsoleThread console;
  int checks = 0;
  LoginGuard guard(console_with("alice"), console.post(), {},
                   [&](std::string_view, std::string_view) -> std::optional<Principal> {
                     ++checks;
                     return std::nullopt;
                   });
  for (int i = 0; i < 5; ++i) {
    guard.login(
        "192.168.10.7", "mallory", "guess", [](LoginOutcome) {}, kStart);
    console.pump(1);
  }
  std::optional<LoginOutcome> outcome;
  guard.login(
      "192.168.10.7", "alice", "guess", [&](LoginOutcome answer) { outcome = std::move(answer); }, kStart);
  ASSERT_TRUE(outcome);
  EXPECT_EQ(outcome->result, Result::Throttled);
  EXPECT_EQ(outcome->retry_after, 1s);
  EXPECT_EQ(outcome->message, "too many failed logins from 192.168.10.7: try again in 1 s");
  EXPECT_EQ(checks, 5);
  EXPECT_EQ(console.waiting(), 0u);
  const LoginStats stats = guard.stats(kStart);
  EXPECT_EQ(stats.throttled, 1u);
  EXPECT_EQ(stats.failed, 5u);
  EXPECT_EQ(stats.addresses_waiting, 1u);
  EXPECT_EQ(stats.users_waiting, 1u);  // mallory too
}

}  // namespace
}  // namespace sms::gateway::console
