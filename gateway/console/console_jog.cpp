#include "gateway/console/console_jog.h"

#include <utility>

namespace sms::gateway::console {

Expected<JogSession> JogSession::press(std::size_t bus, std::string bus_name, const MotionStops& now) {
  if (now.estop_latched) return unexpected(std::string("the e-stop is latched: reset it first; not moved"));
  if (now.tripped) {
    return unexpected("the watchdog of bus " + bus_name +
                      " tripped: re-arm it first (gateway unit coil 2 := 0); not moved");
  }
  if (now.lent) {
    return unexpected("bus " + bus_name + " is stopped for commissioning: start it again first; not moved");
  }
  if (now.blocked) return unexpected("motion on bus " + bus_name + " is blocked (the gateway stops); not moved");
  return JogSession(bus, std::move(bus_name), now);
}

std::optional<std::string> JogSession::ended(const MotionStops& now) const {
  // The press saw the bus unblocked: blocked now, or a newer epoch, means a stop came since. The
  // counts say which (a stop that has been reset since shows only in them).
  if (now.epoch == at_press_.epoch && !now.blocked && now.estops == at_press_.estops && now.trips == at_press_.trips)
    return std::nullopt;
  if (now.estop_latched || now.estops != at_press_.estops)
    return std::string("ended by the e-stop; once it is reset, press again to move");
  if (now.tripped || now.trips != at_press_.trips) {
    return "ended by the watchdog of bus " + bus_name_ + "; once it is re-armed, press again to move";
  }
  if (now.lent) return "ended: bus " + bus_name_ + " was stopped for commissioning";
  return "ended: motion on bus " + bus_name_ + " was stopped";
}

}  // namespace sms::gateway::console
