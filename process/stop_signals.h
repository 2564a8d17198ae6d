#pragma once
// How a program of the project waits to be stopped (sms-gateway, its `forward` tool, sms-sim):
// SIGINT and SIGTERM (and any others the program asks for, such as SIGHUP) are blocked in every
// thread and taken by the main thread with sigwait(), so no handler runs at a random point of a
// random thread and a worker thread never swallows the stop.
//
//   process::StopSignals signals({SIGHUP});  // before any thread starts
//   ... start the threads ...
//   while (signals.wait() == SIGHUP) reload();
#include <initializer_list>
#include <string>

#include <signal.h>

namespace sms::process {

class StopSignals {
 public:
  // Blocks SIGINT, SIGTERM and `also` in the calling thread, and so in every thread it starts
  // afterwards (they inherit its mask): construct it before the first thread starts.
  explicit StopSignals(std::initializer_list<int> also = {});
  // Waits until one of the signals comes; returns its number.
  int wait() const;
  // "Terminated", "Interrupt", ... for the log.
  static std::string name(int signal_number);

 private:
  sigset_t signals_{};
};

}  // namespace sms::process
