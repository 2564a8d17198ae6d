#pragma once
// Password logins of the browser console (docs/CONSOLE.md "Logins"): a backoff after failed
// logins, per source address and per user name, and the password check itself — libsodium's
// Argon2id, about 100 ms of CPU and 64 MiB — on a worker thread of its own behind a short queue,
// never on the console's io thread, which serves the e-stop, the jogs and the WebSockets.
//
//   LoginGuard guard(console_config, post_to_console_thread);
//   guard.login(peer_address, user, password, [](LoginOutcome outcome) { ... });  // console thread
//   LoginStats stats = guard.stats();                                               // any thread
//   guard.stop();  // joins the worker; a check still queued is dropped
//
// `done` is called at once for a login that waits (Throttled) or finds the queue full (Busy);
// after the check, through `post` (on the console thread) for Ok and Failed.
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "config/config.h"
#include "gateway/console/console_access.h"

namespace sms::gateway::console {

struct BackoffLimits {
  // Failures (per address, per user) that cost nothing; each one after them doubles the wait:
  // 1 s after the 5th, 2 s after the 6th, ... up to the maximum.
  unsigned free_failures = 5;
  std::chrono::seconds first_wait{1};
  std::chrono::seconds max_address_wait{300};
  // Shorter for a user name: anyone may fail logins in a user's name and so keep them waiting.
  std::chrono::seconds max_user_wait{60};
  // A count is forgotten this long after its wait ended without another failure.
  std::chrono::seconds forget_after{15 * 60};
  // Bounded memory: source addresses and names that are not console.users tracked at most; past
  // them the entry with the oldest failure goes. The configured users are always tracked.
  std::size_t max_addresses = 1024;
  std::size_t max_unknown_names = 256;
};

// Why a login must wait, and how long (whole seconds, at least 1).
struct Throttle {
  std::chrono::seconds retry_after{1};
  std::string why;  // "too many failed logins from 192.168.10.7"
};

// The failure counts and their waits. Not thread-safe (LoginGuard locks it); the clock is the
// caller's, so tests step it.
class LoginBackoff {
 public:
  using Clock = std::chrono::steady_clock;
  LoginBackoff(std::vector<std::string> known_users, BackoffLimits limits = {});

  // The wait a login from `address` in the name of `user` is under now, if any (the longer one).
  std::optional<Throttle> throttled(std::string_view address, std::string_view user, Clock::time_point now);
  // What succeeded() needs to take an attempt back.
  struct Attempt {
    Clock::time_point at;
    Clock::time_point address_before;  // the address's last failure before it
  };
  // A login about to be checked counts as failed from the start, so that logins checked at the
  // same time cannot each pass the count; succeeded() takes it back.
  Attempt count_attempt(std::string_view address, std::string_view user, Clock::time_point now);
  // The password was right: the user's count is cleared, and the attempt no longer counts for
  // the address (its wait is again the one its earlier failures made).
  void succeeded(std::string_view address, std::string_view user, const Attempt& attempt);
  // Addresses and user names whose logins wait now.
  std::size_t addresses_waiting(Clock::time_point now) const;
  std::size_t users_waiting(Clock::time_point now) const;
  // Entries held (for the memory bound).
  std::size_t tracked() const { return addresses_.size() + users_.size() + unknown_names_.size(); }

  // The key an address is counted under: an IPv4 address as it is, an IPv6 address by its /64
  // (one host often has a whole /64); an IPv4-mapped IPv6 address as IPv4.
  static std::string address_key(std::string_view address);

 private:
  struct Entry {
    unsigned failures = 0;
    Clock::time_point last_failure{};
  };
  using Table = std::map<std::string, Entry, std::less<>>;
  Clock::time_point wait_end(const Entry& entry, std::chrono::seconds max_wait) const;
  void count(Table& table, std::string_view key, std::size_t capacity, std::chrono::seconds max_wait,
             Clock::time_point now);
  Table& user_table(std::string_view user);

  const BackoffLimits limits_;
  std::vector<std::string> known_users_;
  Table addresses_;
  Table users_;          // console.users only
  Table unknown_names_;  // any other name (the same answers: no name is told to exist)
};

struct LoginOutcome {
  enum class Result : std::uint8_t { Ok, Failed, Throttled, Busy };
  Result result = Result::Failed;
  std::optional<Principal> who;         // Ok
  std::chrono::seconds retry_after{0};  // Throttled, Busy
  std::string message;                  // for the page: what happened and what to do
};

struct LoginStats {
  std::uint64_t ok = 0;
  std::uint64_t failed = 0;     // wrong password or unknown user
  std::uint64_t throttled = 0;  // refused at once: the address or the user must wait
  std::uint64_t busy = 0;       // refused at once: the check's queue was full
  std::size_t addresses_waiting = 0;
  std::size_t users_waiting = 0;
};

struct LoginGuardLimits {
  BackoffLimits backoff;
  // Checks waiting for the worker; a login past them is answered Busy at once.
  std::size_t queue_depth = 4;
};

class LoginGuard {
 public:
  using Post = std::function<void(std::function<void()>)>;
  // Checks a name and password: check_login() against console.users unless a test gives another.
  using Check = std::function<std::optional<Principal>(std::string_view user, std::string_view password)>;
  using Done = std::function<void(LoginOutcome)>;

  LoginGuard(const config::ConsoleConfig& console, Post post, LoginGuardLimits limits = {}, Check check = {});
  ~LoginGuard();  // stop()
  LoginGuard(const LoginGuard&) = delete;
  LoginGuard& operator=(const LoginGuard&) = delete;

  // Console thread. `address`: the peer's address as text ("127.0.0.1", "fe80::1").
  void login(std::string_view address, std::string user, std::string password, Done done,
             LoginBackoff::Clock::time_point now = LoginBackoff::Clock::now());
  LoginStats stats(LoginBackoff::Clock::time_point now = LoginBackoff::Clock::now()) const;
  // Idempotent. Checks still queued are dropped (their `done` is never called).
  void stop();

 private:
  struct Job {
    std::string address;
    std::string user;
    std::string password;
    Done done;
    LoginBackoff::Attempt attempt;
  };
  void run();

  const config::ConsoleConfig console_;
  const Post post_;
  const LoginGuardLimits limits_;
  const Check check_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  LoginBackoff backoff_;
  std::deque<Job> queue_;
  LoginStats counts_;
  bool stopping_ = false;
  // Failed logins are logged at most once a second (a flood would fill the journal).
  LoginBackoff::Clock::time_point last_log_{};
  std::uint64_t unlogged_failures_ = 0;
  std::thread worker_;
};

}  // namespace sms::gateway::console
