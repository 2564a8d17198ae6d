#pragma once
// The one way the tests and the benchmarks wait for something to happen: ask a condition every
// kPollInterval until it holds or the timeout passes. The timeout bounds only a failing wait (a
// passing one returns as soon as the condition holds), so it is generous for a loaded machine
// running sanitizers; it is not a speed requirement (speed is measured by bench/, never asserted).
//
// The policy: every wait uses kAwaitTimeout. A caller passes a longer timeout only where what it
// awaits takes longer by design (a port reopened after its reopen period under a flood of
// clients); never a shorter one, which would be a timed assertion. Tests use eventually()
// (tests/support/eventually.h, a GoogleTest assertion); code without GoogleTest (the benchmarks,
// fixtures that throw) uses await_or_throw().
#include <chrono>
#include <stdexcept>
#include <string>
#include <thread>

namespace sms::test {

inline constexpr std::chrono::milliseconds kAwaitTimeout{10'000};
inline constexpr std::chrono::milliseconds kPollInterval{5};

// Whether `condition` held within `timeout` (asked once more at the end, so a slow last poll
// still counts).
template <typename Condition>
bool poll_until(Condition&& condition, std::chrono::milliseconds timeout = kAwaitTimeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (condition()) return true;
    std::this_thread::sleep_for(kPollInterval);
  }
  return condition();
}

// "still not true after 10 s (asked every 5 ms): <what>"
inline std::string await_failure(const std::string& what, std::chrono::milliseconds timeout) {
  const auto count = timeout.count();
  const std::string after = count % 1000 == 0 ? std::to_string(count / 1000) + " s" : std::to_string(count) + " ms";
  return "still not true after " + after + " (asked every " + std::to_string(kPollInterval.count()) +
         " ms): " + (what.empty() ? std::string("the awaited condition") : what);
}

// Waits like poll_until(); throws std::runtime_error naming `what` when the condition never held.
template <typename Condition>
void await_or_throw(Condition&& condition, const std::string& what, std::chrono::milliseconds timeout = kAwaitTimeout) {
  if (!poll_until(condition, timeout)) throw std::runtime_error(await_failure(what, timeout));
}

}  // namespace sms::test
