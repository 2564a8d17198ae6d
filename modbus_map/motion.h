#pragma once
// What makes a servo move and how to stop it, per table, as data (docs/PLC_GUIDE.md "Safety").
// The gateway's safety rules use it three ways, sans I/O:
// - which writes are motion writes (refused while the e-stop is latched or a watchdog tripped),
//   and which writes only stop a motor (allowed then: torque off, brake, sleep, speed 0);
// - what to read from a servo before stopping it (mode, torque, goal block, present position);
// - the bus writes of a safe stop (`hold`, `torque_off`) from those bytes.
//
//   const MotionSpec& spec = motion_spec(TableId::Sts);
//   for (const BusRange& r : spec_context_reads(spec)) ... READ r ...
//   auto stop = plan_safe_stop(spec, StopAction::Hold, ByteOrder::LowFirst, context);
//   // stop->writes: one block write (the stop ramp .. goal speed) or a torque-off write
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"
#include "modbus_map/register_map.h"
#include "protocol/expected.h"

namespace sms::modbus_map {

// What a safe stop does to one servo (config `safe_stop`, docs/PLC_GUIDE.md "Safety").
enum class StopAction : std::uint8_t {
  Hold,       // position modes: goal := present position; speed modes: speed 0; PWM: duty 0
  TorqueOff,  // the motor lets go: a load under gravity falls
  None,       // the gateway leaves the servo alone
};
std::string_view to_string(StopAction action);

// How the servo drives its motor, as far as stopping it goes.
enum class Drive : std::uint8_t { Position, Velocity, Pwm, Step };
std::string_view to_string(Drive drive);  // "position mode", "speed mode", "PWM mode", "step mode"
struct DriveMode {
  std::int32_t value;  // the operating-mode field's value
  Drive drive;
};

// A write that can only stop a motor: allowed while motion is blocked.
struct StoppingWrite {
  std::string_view field;
  std::int32_t value;
};

// A field that lets the motor drive ("no jump on enable", docs/PLC_GUIDE.md "Safety"): the motor
// drives only while every enable field of its table holds its `on` value (the torque switch 1;
// d55d sleep 0 and brake 0). Any other value stops or frees it (0 off, 2 damping, 128 calibrate).
struct EnableField {
  std::string_view field;
  std::int32_t on;
  std::string_view what;  // the enabling write, for the log and docs: "torque on", "wake"
};

// A field of the stop's own ramp and its count for the fastest braking the servo has.
struct RampField {
  std::string_view field;
  std::int32_t fastest;
};

struct MotionSpec {
  TableId table;
  // Operating-mode field; empty: position mode, and when both angle limits are 0 the drive of
  // the one entry of `modes` (none: velocity, d55d wheel mode; scs: PWM).
  std::string_view mode;
  std::span<const DriveMode> modes;
  std::string_view min_limit;
  std::string_view max_limit;
  std::string_view torque;  // torque switch (1 = on); empty: the table has none
  // The goal block, written whole by `hold` so that one SYNC WRITE frame stops every servo of a
  // bus: from goal_position to the last of goal_time / goal_speed (fields between keep their
  // values, read just before).
  std::string_view goal_position;
  std::string_view goal_time;  // PWM duty in PWM mode; empty: none
  std::string_view goal_speed;
  std::string_view present_position;
  StoppingWrite torque_off;  // what `torque_off` writes
  // Fields whose writes can set a motor moving (goals, mode, torque, brake, homing).
  std::span<const std::string_view> motion_fields;
  // Writes of these values are stops, allowed while motion is blocked.
  std::span<const StoppingWrite> stopping_writes;
  StopAction default_stop;  // a servo's `safe_stop` when the configuration names none
  // Fields without which the motor does not drive; writing their `on` value enables motion. The
  // fields that choose the drive (`mode`, or both angle limits) are the other way to start one.
  std::span<const EnableField> enables;
  // The stop's own ramp (docs/SAFETY.md "Stop distance"): `hold` writes these with the goal, in
  // the same frame, so the servo brakes at its fastest (or at the configured stop_deceleration),
  // never at the gentle ramp a move or the PLC left. Empty: the table has none (scs changes
  // speed at once).
  std::span<const RampField> stop_ramp;
  // The axis runs on while the stop frame is on its way and while it brakes at a ramp that takes
  // time: `hold` puts the goal where it will stand (present position + run-on from this speed),
  // so it never drives back.
  std::string_view present_speed;
};

const MotionSpec& motion_spec(TableId id);

// The bus ranges to read before a safe stop: mode (or angle limits), torque, the goal block and
// the present position, merged where they lie close together (one READ on packet tables).
std::vector<BusRange> stop_context_reads(const MotionSpec& spec);

// The bytes read for stop_context_reads(spec), in that order.
struct StopContext {
  std::span<const BusRange> ranges;
  std::span<const protocol::Bytes> data;
};

// How a hold brakes.
struct StopOptions {
  // Skip the "torque already off, nothing to do" rule (the caller is about to switch the torque
  // on: "no jump on enable").
  bool torque_known_on = false;
  // The count written to every stop_ramp field; nullopt: each field's `fastest` (config
  // `stop_deceleration`, docs/SAFETY.md "Stop distance").
  std::optional<std::int32_t> deceleration;
  // Leave the ramp fields as read (the hold before an enabling write: the motor stands, and the
  // PLC's own ramp must survive its torque on).
  bool keep_ramp = false;
  // Seconds from the present position's sample (the servo's answer to the context read) to the
  // stop frame's arrival: the axis runs on v·lead meanwhile, and the goal goes that much ahead
  // too, so a fast axis is not driven back the few steps it moved while the frame was on its way.
  double lead_seconds = 0;
};

struct SafeStopPlan {
  std::vector<BusWrite> writes;  // empty: nothing to do (action none, or torque already off)
  Drive drive = Drive::Position;
  std::string what;  // for the log: "hold (position mode: goal := 1523)"
};
// The writes that stop one servo. `Hold` writes the goal block with the stop ramp; in position
// mode the goal is the present position plus the run-on at that ramp (0 where the fastest is "no
// ramp"). On a servo in step mode (every goal is a move relative to the running target, so no
// goal holds it) it becomes a torque off, said in `what`.
Expected<SafeStopPlan> plan_safe_stop(const MotionSpec& spec, StopAction action, ByteOrder order,
                                      const StopContext& context, const StopOptions& options = {});

// The goal block's range (bus addresses): what `hold` writes, from the first of the stop ramp
// and the goal position to the last of the goal time, the goal speed and the stop ramp.
BusRange goal_block(const MotionSpec& spec);
// Position units an axis at `speed` (counts of its present speed) runs on: `lead_seconds` at that
// speed, then braking at `deceleration` counts of its stop ramp (none where the table has no
// ramp or the count means "no ramp"); `resolution`: d55d's angle resolution as read (the units
// scale with it).
double run_on(const MotionSpec& spec, std::int32_t speed, std::int32_t deceleration, std::int32_t resolution = 0,
              double lead_seconds = 0);
// Whether `count` is a valid stop_deceleration for the table (inside every ramp field's range);
// an error says why not.
std::optional<std::string> check_stop_deceleration(const MotionSpec& spec, std::int32_t count);
// What `torque_off` writes (no read needed).
BusWrite torque_off_write(const MotionSpec& spec, ByteOrder order);

// Why a write plan may not run while motion is blocked, or nullopt when it only stops motors
// (or touches no motion field at all). "goal_position (42)".
std::optional<std::string> motion_in_plan(const MotionSpec& spec, ByteOrder order, const WritePlan& plan);
// Whether writing `field` is a motion write (sync groups name their field).
bool is_motion_field(const MotionSpec& spec, std::string_view field);

// --- "No jump on enable" (docs/PLC_GUIDE.md "Safety") -------------------------------------------
// A write that enables motion — an enable field's `on` value where the servo held another, or a
// drive change of an enabled servo — gets the hold first, so a stale goal, speed or duty left in
// the servo cannot make it move the moment it may. The request's own goal, written after the
// hold, still moves it. The gateway asks may_enable_motion (no I/O), reads the servo
// (enable_context_reads) and writes what plan_enable_hold says, then the request.

// The fields that choose how the motor drives: the mode field, or both angle limits where the
// table has none (d55d wheel mode, scs PWM).
std::vector<std::string_view> drive_fields(const MotionSpec& spec);
// Whether `writes` (staged or not, whatever else they write) put an enable field's `on` value or
// touch a drive field: then the servo's state decides (plan_enable_hold).
bool may_enable_motion(const MotionSpec& spec, ByteOrder order, std::span<const BusWrite> writes);
// What plan_enable_hold needs read: stop_context_reads and every enable field, merged the same way.
std::vector<BusRange> enable_context_reads(const MotionSpec& spec);
// Whether every enable field holds its `on` value in `context`; nullopt when one was not read.
std::optional<bool> motion_enabled(const MotionSpec& spec, ByteOrder order, const StopContext& context);
// The hold to write before `writes`, the servo read as `context` (enable_context_reads):
// - nullopt: none — the writes leave the motor disabled; or it is enabled and keeps its drive (a
//   hold would cancel the move under way); or it is enabled into step mode (every goal is relative);
// - the drive's hold (safe stop `hold`) when the writes enable a disabled motor in its drive;
// - on a drive change: goal := present position, speed and duty := 0 (a hold in the old drive and
//   nothing stale in the new), or torque off when the drive was step mode (no goal holds there);
// - an error when the state was not read whole or is undocumented, or when the writes leave step
//   mode and enable the motor at once (no hold is safe in both drives: write the mode first).
Expected<std::optional<SafeStopPlan>> plan_enable_hold(const MotionSpec& spec, ByteOrder order,
                                                       const StopContext& context, std::span<const BusWrite> writes);

}  // namespace sms::modbus_map
