// The safe stops owed to servos a stop did not reach: the torque off their engine sends first
// when they are back (BusEngine::owe_stop).
#include "gateway/units/safety_impl.h"

#include <spdlog/spdlog.h>

#include "gateway/units/unit_router.h"

namespace sms::gateway {

std::string SafetySupervisor::Impl::owed_text() const {
  std::size_t owed = 0;
  for (const auto& bus : buses_) owed += bus->engine->owed_stop_count();
  if (owed == 0) return {};
  return "; " + std::to_string(owed) + " servo(s) still owe their safe stop and refuse motion until they have taken it";
}

// The torque off a servo is owed when its stop did not reach it (BusEngine::owe_stop).
OwedStop SafetySupervisor::Impl::owed_stop_for(const BusSafety& bus, const StopTarget& target,
                                               std::string_view reason) const {
  const auto write = modbus_map::torque_off_write(*target.spec, target.order);
  const bool answers = answers_writes(target.spec->table, target.response_level, *bus.engine, target.servo_id);
  return OwedStop{WriteOp{target.servo_id, write.address, write.data, false, answers, 0}, std::string(reason)};
}

std::string SafetySupervisor::Impl::owe_stops(BusSafety& bus, const std::vector<std::size_t>& targets,
                                              std::string_view reason) {
  std::string servos;
  for (const std::size_t t : targets) {
    bus.engine->owe_stop(owed_stop_for(bus, bus.targets[t], reason));
    servos += (servos.empty() ? "" : ", ") + std::to_string(bus.targets[t].servo_id);
  }
  return servos;
}

// The stops the state file says were owed before the restart: owed again, sent before anything
// else on their bus (the engines have not started yet).
void SafetySupervisor::Impl::restore_owed(const SafetyStateRecord& state) {
  for (const auto& owed : state.owed_stops) {
    BusSafety* bus = bus_named(owed.bus);
    const StopTarget* target = nullptr;
    if (bus != nullptr) {
      for (const auto& t : bus->targets) {
        if (t.servo_id == owed.servo) target = &t;
      }
    }
    if (target == nullptr) {
      spdlog::warn(
          "safety: {} says servo {} on bus `{}` was owed its safe stop ({}), but the configuration has no such "
          "servo now: ignored; make sure that servo is stopped",
          state_path_, owed.servo, owed.bus, owed.why);
      continue;
    }
    OwedStop stop = owed_stop_for(*bus, *target, owed.why);
    // The servo's answers are not known before discovery: as they were when the stop was owed.
    if (!target->response_level) stop.write.expect_reply = owed.answers_writes;
    bus->engine->owe_stop(std::move(stop));
    spdlog::warn(
        "safety: bus {}: servo {} was owed its safe stop ({}) before the restart ({}): it is sent before "
        "anything else on the bus, and motion writes to the servo are refused until it has taken it",
        bus->name, owed.servo, owed.why, state_path_);
  }
}

}  // namespace sms::gateway
