#include "process/stop_signals.h"

#include <pthread.h>

#include <cstring>
#include <string>

namespace sms::process {

StopSignals::StopSignals(std::initializer_list<int> also) {
  sigemptyset(&signals_);
  sigaddset(&signals_, SIGINT);
  sigaddset(&signals_, SIGTERM);
  for (const int signal_number : also) sigaddset(&signals_, signal_number);
  pthread_sigmask(SIG_BLOCK, &signals_, nullptr);
}

int StopSignals::wait() const {
  int signal_number = 0;
  sigwait(&signals_, &signal_number);  // fails only for a set of invalid signals, which this is not
  return signal_number;
}

std::string StopSignals::name(int signal_number) {
  const char* text = strsignal(signal_number);
  return text != nullptr ? text : "signal " + std::to_string(signal_number);
}

}  // namespace sms::process
