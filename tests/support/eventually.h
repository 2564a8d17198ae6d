#pragma once
// eventually(): a GoogleTest assertion that a condition comes true, with the one wait policy of
// tests/support/await.h (kAwaitTimeout, kPollInterval). On failure it names what was awaited:
//   ASSERT_TRUE(eventually([&] { return engine->discovered(); }, "the engine's discovery"));
//   -> still not true after 10 s (asked every 5 ms): the engine's discovery
// Without `what` the message still says how long it waited; GoogleTest adds the expression.
#include <gtest/gtest.h>

#include <chrono>
#include <string>

#include "tests/support/await.h"

namespace sms::test {

template <typename Condition>
::testing::AssertionResult eventually(Condition&& condition, const std::string& what = {},
                                      std::chrono::milliseconds timeout = kAwaitTimeout) {
  if (poll_until(condition, timeout)) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << await_failure(what, timeout);
}

// The same with the timeout second, for the few waits that take longer than kAwaitTimeout by
// design (await.h says when).
template <typename Condition>
::testing::AssertionResult eventually(Condition&& condition, std::chrono::milliseconds timeout,
                                      const std::string& what = {}) {
  return eventually(condition, what, timeout);
}

}  // namespace sms::test
