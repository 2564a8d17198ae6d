#pragma once
// The one safety rule of every hold-to-run move the console makes (docs/CONSOLE.md "Jog panel"), the
// position and the speed jog alike: a move is a session that begins at a press and remembers its
// bus's motion stops then (SafetySupervisor::motion_stops). An e-stop latch, a trip of the bus's
// watchdog, or anything else that blocked the bus's motion since the press ends the session for
// good: the servo is stopped as on a release, the page is told why, and a reset or a re-arm
// moves nothing — only a new press does. It compares counts, not the state now, so a latch and
// a reset between two looks are seen as well as a latch that still holds.
//
//   auto session = JogSession::press(bus_index, bus_name, safety.motion_stops(bus_index));
//   if (!session) refuse(session.error());                          // "the e-stop is latched ..."
//   if (auto why = session->ended(safety.motion_stops(bus_index))) stop(*why);  // every step
#include <cstddef>
#include <optional>
#include <string>

#include "gateway/units/safety.h"
#include "protocol/expected.h"

namespace sms::gateway::console {

class JogSession {
 public:
  // A press on a servo of bus `bus` (named `bus_name`) whose motion stops are `now`: the session,
  // or why the press moves nothing (the bus's motion is blocked now).
  static Expected<JogSession> press(std::size_t bus, std::string bus_name, const MotionStops& now);

  // nullopt while the session may move; else why it is over, for the page and the log
  // ("ended by the e-stop ...", "ended by the watchdog of bus arm ..."). Once over, always over.
  std::optional<std::string> ended(const MotionStops& now) const;

  std::size_t bus() const { return bus_; }

 private:
  JogSession(std::size_t bus, std::string bus_name, const MotionStops& at_press)
      : bus_(bus), bus_name_(std::move(bus_name)), at_press_(at_press) {}

  std::size_t bus_;
  std::string bus_name_;
  MotionStops at_press_;
};

}  // namespace sms::gateway::console
