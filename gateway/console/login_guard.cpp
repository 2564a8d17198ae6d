#include "gateway/console/login_guard.h"

#include <arpa/inet.h>
#include <sodium.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>

#include <spdlog/spdlog.h>

#include "gateway/console/console_request.h"

namespace sms::gateway::console {

namespace {

using Clock = LoginBackoff::Clock;

constexpr int kWorkerNice = 10;

// Whole seconds to wait, rounded up, at least 1 (for Retry-After).
std::chrono::seconds seconds_until(Clock::time_point end, Clock::time_point now) {
  const auto left = std::chrono::ceil<std::chrono::seconds>(end - now);
  return std::max(left, std::chrono::seconds{1});
}

}  // namespace

// --- LoginBackoff -------------------------------------------------------------------------------

LoginBackoff::LoginBackoff(std::vector<std::string> known_users, BackoffLimits limits)
    : limits_(limits), known_users_(std::move(known_users)) {}

std::string LoginBackoff::address_key(std::string_view address) {
  std::string text(address);
  in6_addr v6{};
  if (inet_pton(AF_INET6, text.c_str(), &v6) == 1) {
    static constexpr unsigned char kMapped[12] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xFF, 0xFF};
    char out[INET6_ADDRSTRLEN] = {};
    if (std::memcmp(v6.s6_addr, kMapped, sizeof kMapped) == 0) {
      in_addr v4{};
      std::memcpy(&v4, v6.s6_addr + 12, 4);
      inet_ntop(AF_INET, &v4, out, sizeof out);
      return out;
    }
    std::memset(v6.s6_addr + 8, 0, 8);
    inet_ntop(AF_INET6, &v6, out, sizeof out);
    return std::string(out) + "/64";
  }
  return text;  // IPv4 as it is (or whatever the peer's address is, not parsed)
}

Clock::time_point LoginBackoff::wait_end(const Entry& entry, std::chrono::seconds max_wait) const {
  if (entry.failures < limits_.free_failures) return entry.last_failure;
  const unsigned doublings = std::min(entry.failures - limits_.free_failures, 30u);
  const auto wait = std::min<std::chrono::seconds>(limits_.first_wait * (std::int64_t{1} << doublings), max_wait);
  return entry.last_failure + wait;
}

LoginBackoff::Table& LoginBackoff::user_table(std::string_view user) {
  const bool known = std::find(known_users_.begin(), known_users_.end(), user) != known_users_.end();
  return known ? users_ : unknown_names_;
}

std::optional<Throttle> LoginBackoff::throttled(std::string_view address, std::string_view user,
                                                Clock::time_point now) {
  std::optional<Throttle> throttle;
  if (const auto it = addresses_.find(address); it != addresses_.end()) {
    const auto end = wait_end(it->second, limits_.max_address_wait);
    if (now < end) throttle = Throttle{seconds_until(end, now), "too many failed logins from " + printable(address)};
  }
  const Table& names = user_table(user);
  if (const auto it = names.find(user); it != names.end()) {
    const auto end = wait_end(it->second, limits_.max_user_wait);
    if (now < end && (!throttle || seconds_until(end, now) > throttle->retry_after)) {
      throttle = Throttle{seconds_until(end, now), "too many failed logins for user `" + printable(user, 64) + "`"};
    }
  }
  return throttle;
}

void LoginBackoff::count(Table& table, std::string_view key, std::size_t capacity, std::chrono::seconds max_wait,
                         Clock::time_point now) {
  const auto forgotten = [&](const Entry& entry) { return now >= wait_end(entry, max_wait) + limits_.forget_after; };
  auto it = table.find(key);
  if (it == table.end()) {
    if (table.size() >= capacity) std::erase_if(table, [&](const auto& item) { return forgotten(item.second); });
    if (table.size() >= capacity && !table.empty()) {
      // Still full: the entry whose last failure is the oldest makes room.
      table.erase(std::min_element(table.begin(), table.end(), [](const auto& a, const auto& b) {
        return a.second.last_failure < b.second.last_failure;
      }));
    }
    it = table.emplace(std::string(key), Entry{}).first;
  } else if (forgotten(it->second)) {
    it->second.failures = 0;
  }
  ++it->second.failures;
  it->second.last_failure = now;
}

LoginBackoff::Attempt LoginBackoff::count_attempt(std::string_view address, std::string_view user,
                                                  Clock::time_point now) {
  Attempt attempt{now, Clock::time_point{}};
  if (const auto it = addresses_.find(address); it != addresses_.end())
    attempt.address_before = it->second.last_failure;
  count(addresses_, address, limits_.max_addresses, limits_.max_address_wait, now);
  Table& names = user_table(user);
  const std::size_t capacity = &names == &users_ ? known_users_.size() : limits_.max_unknown_names;
  count(names, user, capacity, limits_.max_user_wait, now);
  return attempt;
}

void LoginBackoff::succeeded(std::string_view address, std::string_view user, const Attempt& attempt) {
  if (const auto it = users_.find(user); it != users_.end()) users_.erase(it);
  const auto it = addresses_.find(address);
  if (it == addresses_.end() || it->second.failures == 0) return;
  if (--it->second.failures == 0) {
    addresses_.erase(it);
  } else if (it->second.last_failure == attempt.at) {
    it->second.last_failure = attempt.address_before;  // no other attempt came since
  }
}

std::size_t LoginBackoff::addresses_waiting(Clock::time_point now) const {
  return static_cast<std::size_t>(std::count_if(addresses_.begin(), addresses_.end(), [&](const auto& item) {
    return now < wait_end(item.second, limits_.max_address_wait);
  }));
}

std::size_t LoginBackoff::users_waiting(Clock::time_point now) const {
  std::size_t waiting = 0;
  for (const Table* table : {&users_, &unknown_names_}) {
    for (const auto& [name, entry] : *table) waiting += now < wait_end(entry, limits_.max_user_wait) ? 1 : 0;
  }
  return waiting;
}

// --- LoginGuard ---------------------------------------------------------------------------------

namespace {

std::vector<std::string> user_names(const config::ConsoleConfig& console) {
  std::vector<std::string> names;
  for (const auto& user : console.users) names.push_back(user.name);
  return names;
}

}  // namespace

LoginGuard::LoginGuard(const config::ConsoleConfig& console, Post post, LoginGuardLimits limits, Check check)
    : console_(console),
      post_(std::move(post)),
      limits_(limits),
      check_(check ? std::move(check) : Check([this](std::string_view user, std::string_view password) {
        return check_login(console_, user, password);
      })),
      backoff_(user_names(console), limits.backoff) {}

LoginGuard::~LoginGuard() { stop(); }

void LoginGuard::login(std::string_view address, std::string user, std::string password, Done done,
                       Clock::time_point now) {
  std::unique_lock lock(mutex_);
  const std::string key = LoginBackoff::address_key(address);
  if (const auto wait = backoff_.throttled(key, user, now)) {
    ++counts_.throttled;
    lock.unlock();
    return done(LoginOutcome{LoginOutcome::Result::Throttled, std::nullopt, wait->retry_after,
                             wait->why + ": try again in " + std::to_string(wait->retry_after.count()) + " s"});
  }
  if (stopping_ || queue_.size() >= limits_.queue_depth) {
    ++counts_.busy;
    lock.unlock();
    return done(LoginOutcome{LoginOutcome::Result::Busy, std::nullopt, std::chrono::seconds{1},
                             "the console is busy checking other logins: try again in 1 s"});
  }
  const auto attempt = backoff_.count_attempt(key, user, now);
  queue_.push_back(Job{std::string(address), std::move(user), std::move(password), std::move(done), attempt});
  // The worker starts with the first login: a console without password users never has one.
  if (!worker_.joinable()) worker_ = std::thread([this] { run(); });
  lock.unlock();
  wake_.notify_one();
}

void LoginGuard::run() {
  // Checks give way to the gateway's own threads (the console's, the io thread, the buses) when
  // the CPUs are short: a flood of logins then slows the logins, not the e-stop. Linux's nice is
  // per thread; failing to lower it changes nothing else.
  (void)setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), kWorkerNice);
  for (;;) {
    Job job;
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
      if (stopping_) return;
      job = std::move(queue_.front());
      queue_.pop_front();
    }
    std::optional<Principal> who;
    std::string trouble;
    try {
      who = check_(job.user, job.password);
    } catch (const std::exception& error) {
      trouble = error.what();  // libsodium out of memory: a failure to the page, the reason in the log
    }
    sodium_memzero(job.password.data(), job.password.size());
    const auto now = Clock::now();
    LoginOutcome outcome;
    std::string log_line;
    {
      std::lock_guard lock(mutex_);
      const std::string key = LoginBackoff::address_key(job.address);
      if (who) {
        backoff_.succeeded(key, job.user, job.attempt);
        ++counts_.ok;
        outcome = LoginOutcome{LoginOutcome::Result::Ok, std::move(who), std::chrono::seconds{0}, ""};
      } else {
        ++counts_.failed;
        outcome = LoginOutcome{
            LoginOutcome::Result::Failed, std::nullopt, std::chrono::seconds{0},
            trouble.empty() ? "unknown user or wrong password" : "the console could not check the password: try again"};
        // At most a line a second, with the failures it left out since the last one.
        if (now - last_log_ >= std::chrono::seconds{1} || last_log_ == Clock::time_point{}) {
          log_line = "console: failed login for user `" + printable(job.user, 64) + "` from " + printable(job.address);
          if (!trouble.empty()) log_line += " (the check failed: " + trouble + ")";
          if (const auto wait = backoff_.throttled(key, job.user, now)) {
            log_line += "; " + wait->why + ": logins wait " + std::to_string(wait->retry_after.count()) + " s";
          }
          if (unlogged_failures_ > 0) {
            log_line += " (" + std::to_string(unlogged_failures_) + " more failed logins since the last such line)";
          }
          last_log_ = now;
          unlogged_failures_ = 0;
        } else {
          ++unlogged_failures_;
        }
      }
    }
    if (!log_line.empty()) spdlog::warn("{}", log_line);
    post_([done = std::move(job.done), outcome = std::move(outcome)]() mutable { done(std::move(outcome)); });
  }
}

LoginStats LoginGuard::stats(Clock::time_point now) const {
  std::lock_guard lock(mutex_);
  LoginStats stats = counts_;
  stats.addresses_waiting = backoff_.addresses_waiting(now);
  stats.users_waiting = backoff_.users_waiting(now);
  return stats;
}

void LoginGuard::stop() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (worker_.joinable()) worker_.join();
  std::deque<Job> dropped;
  {
    std::lock_guard lock(mutex_);
    dropped.swap(queue_);
  }
}

}  // namespace sms::gateway::console
