#pragma once
// How a bus thread sleeps between jobs: on an eventfd in ppoll, woken by notify() from any
// thread or by a deadline (the next poll cycle, the next reopen attempt). A notify() that comes
// before the sleep is not lost: the eventfd stays readable until the sleeper has seen it.
// An eventfd rather than a condition variable, on measurement (docs/DECISIONS.md "Threading
// model"): the bus thread's wake-up on a client request is the first step of every live write.
#include <chrono>
#include <optional>

namespace sms::gateway {

class Wakeup {
 public:
  Wakeup();  // throws std::system_error when no eventfd can be made
  ~Wakeup();
  Wakeup(const Wakeup&) = delete;
  Wakeup& operator=(const Wakeup&) = delete;

  void notify();
  // Returns after notify() (since the last wait) or at `deadline`; nullopt: no deadline.
  void wait(std::optional<std::chrono::steady_clock::time_point> deadline);
  // The eventfd, for a thread that waits on it together with other descriptors in its own ppoll
  // (readable after notify()); wait() with a past deadline then consumes the notifications.
  int native_handle() const { return fd_; }

 private:
  int fd_ = -1;
};

}  // namespace sms::gateway
