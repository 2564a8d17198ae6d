#pragma once
// Motion safety (docs/PLC_GUIDE.md "Safety"): per-bus watchdogs, the e-stop latch, safe stops, and the start
// and stop actions. The supervisor runs its own thread, so a watchdog trips on time even while
// the Modbus io thread is busy; every safe stop goes to the bus engines at Priority::Safety
// (before any client work, never refused for a full queue).
//
// Rules, in one place:
// - A bus's watchdog is armed at start and after a re-arm, and starts counting at the first
//   feed or the first motion write on the bus. `timeout` after the last feed it trips: the bus's
//   MotionGate blocks (new motion writes: 0x04; queued ones are dropped by the engine), every
//   servo of the bus gets its safe stop once, and the state stays `tripped` until a re-arm.
//   Only a write the gateway carried out feeds it (the unit router and the gateway unit call
//   feed_write() on success).
// - The e-stop latch blocks every bus and stops every servo; only a reset clears it, and a reset
//   (like a re-arm) moves nothing.
// - Whether a bus's motion is blocked is computed from the whole state (shutdown, latch, its
//   watchdog) after every transition, under one lock, so what a client reads never disagrees
//   with what the gate enforces.
// - The latch, the tripped watchdogs and the owed safe stops are kept in `<state_dir>/safety.state`
//   (the latch and trips written before the request that changed them is answered, the owed
//   stops on every change of an engine's owed set) and restored at start: a restart or a crash
//   does not release them, a restored latch or trip stops its servos again at start, and a
//   restored owed stop is owed again (sent before anything else, whatever on_start says). A
//   file that is not a complete state of the exact schema latches the e-stop. A save that fails
//   is retried every second and shows in facts().state_not_persisted until one succeeds.
// - A safe stop reads each servo's mode, torque, goal block and present position (one SYNC READ
//   frame for a feetech bus's servos, a servo silent in it read on its own; else one READ per
//   servo), then writes: on packet buses one SYNC WRITE frame per distinct write shape,
//   on modbus-rtu buses one write per servo in unit order. A servo that cannot be read gets its
//   torque switched off. A servo the stop could not reach (bus down, offline, no answer; on packet
//   buses also one whose state could not be read, since a broadcast is never acknowledged) is
//   owed its torque off: its engine sends it when the servo is back, before anything else, until
//   it is acknowledged (BusEngine::owe_stop). Failed stops are counted, not counted as stops.
//
//   SafetySupervisor safety(config, engines, gates);
//   safety.start();                               // restored latch/trips, on_start, watchdog thread
//   auto epoch = safety.admit_motion(bus);        // io thread, before a motion write
//   safety.feed_write(bus);                       // io thread, once a write was carried out
//   safety.stop_for_shutdown(2s);                 // on_stop actions, then no more motion
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/motion_gate.h"
#include "gateway/service/rate_limited_log.h"
#include "protocol/expected.h"

namespace sms::gateway {

enum class WatchdogState : std::uint8_t {
  Off = 0,      // no watchdog on this bus
  Armed = 1,    // waiting for the first feed or motion write
  Running = 2,  // counting: tripped `timeout` after the last feed
  Tripped = 3,  // stopped the bus; motion refused until re-armed
};
std::string_view to_string(WatchdogState state);

// What a safe stop was for (logs, unit 255 register, metrics).
enum class StopCause : std::uint8_t { None = 0, Watchdog = 1, EStop = 2, Start = 3, Shutdown = 4, Commissioning = 5 };
std::string_view to_string(StopCause cause);

struct BusSafetyFacts {
  WatchdogState state = WatchdogState::Off;
  std::optional<std::chrono::milliseconds> since_feed;  // nullopt: never fed
  std::optional<std::chrono::milliseconds> since_trip;  // since its watchdog last tripped; nullopt: never
  std::chrono::milliseconds timeout{0};
  std::uint64_t trips = 0;
  std::uint64_t stops = 0;  // safe stops performed on this bus, every cause
  StopCause last_cause = StopCause::None;
  std::optional<std::chrono::microseconds> last_stop_latency;  // of the last stop that succeeded
  bool motion_blocked = false;
  std::uint64_t failed_stops = 0;  // stops that could not reach every servo when performed
  std::size_t owed_stops = 0;      // servos owed their stop right now
  bool lent = false;               // its line is lent to commissioning (SafetySupervisor::lend_bus)
};

struct SafetyFacts {
  bool estop_latched = false;
  std::uint64_t estops = 0;
  std::vector<BusSafetyFacts> buses;
  // The last change of the latch, the trips or the owed stops could not be written to the state
  // file, and no save has succeeded since: a restart now would forget it (docs/SAFETY.md "When
  // the state cannot be saved"). Retried every second until a save succeeds.
  bool state_not_persisted = false;
  std::string state_problem;  // why, while state_not_persisted
};

// One bus's motion stops as an operator's hold-to-run move checks them (the browser console's jog,
// docs/CONSOLE.md "Jog panel"): a move pressed in one epoch may not move in another. Atomics only.
struct MotionStops {
  MotionEpoch epoch = 0;  // the bus's motion gate epoch: grows whenever its motion is blocked
  bool blocked = false;   // motion writes on the bus are refused now, because of:
  bool estop_latched = false;
  bool tripped = false;      // its watchdog
  bool lent = false;         // its line is lent to commissioning
  std::uint64_t estops = 0;  // e-stop latches since start
  std::uint64_t trips = 0;   // trips of its watchdog since start
};

// Refused motion writes, logged as a warning at most once a second (a PLC writing cyclically
// into a latched gateway would otherwise fill the log). io thread only.
class MotionRefusalLog {
 public:
  void refused(std::string_view who, std::uint8_t function, std::string_view why);

 private:
  RateLimitedLog log_;
};

class SafetySupervisor;
class Reply;
// The safety rules' admission of a motion write on `bus` for every way in (servo, passthrough
// and gateway units): its epoch, or nullopt after answering 0x04 (MotionBlocked) with the refusal
// logged through `log` (at most once a second), naming `what`.
std::optional<MotionEpoch> admit_or_refuse(SafetySupervisor& safety, MotionRefusalLog& log, std::size_t bus,
                                           std::string_view what, std::uint8_t function, const Reply& reply);

class SafetySupervisor {
 public:
  // `engines[i]` runs config.buses[i]; `gates[i]` is the gate its engine checks
  // (BusSettings::motion_gate). Reads the state file (config::effective_state_dir) and throws
  // std::runtime_error when its directory is unusable; an unreadable or damaged state file
  // latches the e-stop (said in the log) rather than start unprotected. Restored owed stops go
  // into the engines here: construct it before the engines start, so they are sent first.
  SafetySupervisor(const config::Config& config, std::vector<BusEngine*> engines,
                   std::vector<std::shared_ptr<MotionGate>> gates);
  ~SafetySupervisor();  // stops the thread; no stop is performed
  SafetySupervisor(const SafetySupervisor&) = delete;
  SafetySupervisor& operator=(const SafetySupervisor&) = delete;

  // Starts the watchdog thread and performs each bus's on_start action. Call after the engines
  // have started.
  void start();
  // SIGTERM / SIGINT: blocks motion on every bus, performs each bus's on_stop action and waits
  // for the frames (at most `bound`). Call before the engines stop. Idempotent.
  void stop_for_shutdown(std::chrono::milliseconds bound);

  // --- the Modbus side (io thread) ---------------------------------------------------------------
  // A write for a unit on `bus` was carried out (feeds a watchdog whose feed is any_write).
  void feed_write(std::size_t bus);
  // Holding register 1000 + bus written: feeds when `value` differs from the last one.
  void feed_heartbeat(std::size_t bus, std::uint16_t value);
  std::optional<std::uint16_t> heartbeat_value(std::size_t bus) const;
  // Before a motion write on `bus`: the epoch the write carries, or why it is refused (the
  // caller answers 0x04 and logs it). An armed watchdog starts counting here.
  Expected<MotionEpoch> admit_motion(std::size_t bus);
  // Why a motion write on `bus` (to servo `servo`, when given: also its owed safe stop) would be
  // refused now, in admit_motion's words; nullopt: it would be admitted. Starts nothing: the
  // browser console asks it after a 0x04 to name the rule that refused the write.
  std::optional<std::string> motion_refusal(std::size_t bus, std::optional<std::uint8_t> servo = std::nullopt) const;

  // Gateway unit coil 1: latch and stop every bus; `done(ok)` runs through `post` once every
  // stop frame has been sent (ok false when a bus could not take its frames).
  using PostFn = std::function<void(std::function<void()>)>;
  // `who` names the client in the log ("a Modbus TCP client", "the Sparkplug host (NCMD/DCMD)").
  void estop(const PostFn& post, std::function<void(bool ok)> done, std::string_view who = "a Modbus TCP client");
  void reset_estop(std::string_view who = "a Modbus TCP client");
  // The browser console stops bus `bus` to lend its line to commissioning (docs/CONSOLE.md): motion
  // on the bus is refused from now on and every servo of the bus gets its safe stop (one it could
  // not take stays owed); `done(ok)` runs on the safety thread once the stop frames went out (ok
  // false: some servo was not reached). Not kept in the state file: a restart runs the bus again.
  void lend_bus(std::size_t bus, std::string_view who, std::function<void(bool ok)> done);
  // One servo's `hold`, as every safe stop writes it (read, then the goal block with the stop
  // ramp), for an operator's move that ends (the browser console's hold-to-run released): it
  // blocks nothing and is not counted as a stop of the bus. A servo it could not reach is owed its
  // stop. `done(ok)` runs on the safety thread (ok false: not reached, or no such servo).
  void hold_servo(std::size_t bus, std::uint8_t servo_id, std::string_view who, std::function<void(bool ok)> done);
  // The bus is back from commissioning: motion is admitted again (unless the latch or a trip
  // says otherwise). Moves nothing.
  void return_bus(std::size_t bus, std::string_view who);
  // Gateway unit coil 2 := 0: every tripped watchdog back to armed. Moves nothing.
  void rearm_watchdogs(std::string_view who = "a Modbus TCP client");

  SafetyFacts facts() const;
  // Bus `bus`'s motion stops now; any thread, no lock (read at every step of a hold-to-run move).
  MotionStops motion_stops(std::size_t bus) const;
  bool estop_latched() const;
  // Where the latch and the tripped watchdogs are kept; empty: not kept.
  const std::string& state_file() const;
  bool any_tripped() const;
  std::size_t bus_count() const;
  std::optional<std::chrono::milliseconds> watchdog_timeout(std::size_t bus) const;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
