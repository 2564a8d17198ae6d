#pragma once
// The simulator's record of a servo's last goal write (sms-sim's `motion ID`, simulator/control_server.h):
// the witness of timed moves and of stops; and of the times the machine held the simulator (`holds`).
#include <chrono>
#include <sstream>
#include <stdexcept>
#include <string>

#include "tests/support/processes.h"

namespace sms::e2e {

struct Motion {
  long long started_us = -1;  // when the last goal was written in position mode (steady clock)
  long long arrived_us = -1;  // when the motor then reached it; -1: not (yet)
  long position = 0;
  long goal = 0;
  long at_goal_write = 0;     // where the motor was when that goal was written
  long read_before_goal = 0;  // where it was when it answered the last read before that write
  bool reversed = false;      // it turned back since its last command
  long turned_back = 0;       // how far, from the farthest point it reached
  long heartbeat_stops = 0;   // d55d: how often its heartbeat stopped it
};

// How far the motor ran between answering the last read before its last goal write and that
// write's arrival. A stop computes its hold from that read, plus the run-on it expects while its
// frame is on the way; where a loaded host held the frame back longer, the axis ran on further and
// the servo pulls back by that much. A stop's bounds allow this much more (never the hundreds of
// steps of a run-on on the move's own ramp, which is what they are there to catch).
inline long run_on_since_read(const Motion& motion) {
  const long run_on = motion.at_goal_write - motion.read_before_goal;
  return run_on < 0 ? -run_on : run_on;
}

inline Motion motion_of(test::SimProcess& sim, int id) {
  const std::string reply = sim.control("motion " + std::to_string(id));
  Motion motion;
  std::istringstream words(reply);
  for (std::string word; words >> word;) {
    const auto equals = word.find('=');
    if (equals == std::string::npos) throw std::runtime_error("sms-sim motion: " + reply);
    const std::string key = word.substr(0, equals);
    const std::string value = word.substr(equals + 1);
    const long long number = value == "-" ? -1 : std::stoll(value);
    if (key == "started_us") motion.started_us = number;
    if (key == "arrived_us") motion.arrived_us = number;
    if (key == "position") motion.position = static_cast<long>(number);
    if (key == "goal") motion.goal = static_cast<long>(number);
    if (key == "at_goal_write") motion.at_goal_write = static_cast<long>(number);
    if (key == "read_before_goal") motion.read_before_goal = static_cast<long>(number);
    if (key == "reversed") motion.reversed = number != 0;
    if (key == "turned_back") motion.turned_back = static_cast<long>(number);
    if (key == "heartbeat_stops") motion.heartbeat_stops = static_cast<long>(number);
  }
  return motion;
}

// Whether the machine held the simulator's bus thread `at_least` in one go, in a hold that ended
// after `since` (sms-sim's `holds`): a servo silent then was silent by the machine's doing, which
// the product answers by its rule (retries, then offline), not a fault of the gateway's.
inline bool sim_held(test::SimProcess& sim, std::chrono::microseconds at_least,
                     std::chrono::steady_clock::time_point since) {
  const std::string reply = sim.control("holds");
  if (reply == "none") return false;
  const long long since_us = std::chrono::duration_cast<std::chrono::microseconds>(since.time_since_epoch()).count();
  std::istringstream words(reply);
  for (std::string word; words >> word;) {
    const auto colon = word.find(':');
    if (colon == std::string::npos) throw std::runtime_error("sms-sim holds: " + reply);
    if (std::stoll(word.substr(0, colon)) >= since_us && std::stoll(word.substr(colon + 1)) >= at_least.count()) {
      return true;
    }
  }
  return false;
}

}  // namespace sms::e2e
