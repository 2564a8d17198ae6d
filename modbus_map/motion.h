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
//   // stop->writes: one block write (goal position .. goal speed) or a torque-off write
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
struct DriveMode {
  std::int32_t value;  // the operating-mode field's value
  Drive drive;
};

// A write that can only stop a motor: allowed while motion is blocked.
struct StoppingWrite {
  std::string_view field;
  std::int32_t value;
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

struct SafeStopPlan {
  std::vector<BusWrite> writes;  // empty: nothing to do (action none, or torque already off)
  Drive drive = Drive::Position;
  std::string what;  // for the log: "hold (position mode: goal := 1523)"
};
// The writes that stop one servo. `Hold` on a servo in step mode (every goal is a move relative
// to the running target, so no goal holds it) becomes a torque off, said in `what`.
// `torque_known_on`: skip the "torque already off, nothing to do" rule (the caller is about
// to switch the torque on: "no jump on enable").
Expected<SafeStopPlan> plan_safe_stop(const MotionSpec& spec, StopAction action, ByteOrder order,
                                      const StopContext& context, bool torque_known_on = false);

// The goal block's range (bus addresses): what `hold` writes.
BusRange goal_block(const MotionSpec& spec);
// What `torque_off` writes (no read needed).
BusWrite torque_off_write(const MotionSpec& spec, ByteOrder order);

// Why a write plan may not run while motion is blocked, or nullopt when it only stops motors
// (or touches no motion field at all). "goal_position (42)".
std::optional<std::string> motion_in_plan(const MotionSpec& spec, ByteOrder order, const WritePlan& plan);
// Whether writing `field` is a motion write (sync groups name their field).
bool is_motion_field(const MotionSpec& spec, std::string_view field);

// Whether the plan switches the torque on (writes 1 to the torque field), staged or not, whatever
// else it writes: then the gateway holds the goal block first where the torque is off ("no jump
// on enable", docs/PLC_GUIDE.md "Safety"); the request's own goal, written after the hold, still moves it.
bool switches_torque_on(const MotionSpec& spec, ByteOrder order, const WritePlan& plan);
// Whether the servo's torque is on in `context` (stop_context_reads); nullopt when the table has
// no torque switch or it was not read.
std::optional<bool> torque_on(const MotionSpec& spec, ByteOrder order, const StopContext& context);

}  // namespace sms::modbus_map
