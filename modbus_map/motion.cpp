#include "modbus_map/motion.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>

#include "modbus_map/tables.h"
#include "modbus_map/tables/common.h"
#include "modbus_map/timed_move.h"

namespace sms::modbus_map {
namespace {

// sts: 0 position, 1 constant speed, 2 open-loop PWM, 3 step (docs/PROTOCOL.md §2.1 address 33).
constexpr DriveMode kStsModes[] = {{0, Drive::Position}, {1, Drive::Velocity}, {2, Drive::Pwm}, {3, Drive::Step}};
// sms1: 0 servo, 1 motor speed, 2 torque (run_time is the signed torque) (docs/PROTOCOL.md §2.2 address 35).
constexpr DriveMode kSms1Modes[] = {{0, Drive::Position}, {1, Drive::Velocity}, {2, Drive::Pwm}};
// SMSMB: 0 servo, 1 constant speed, 3 torque off on arrival (a position mode), 4 stepper (§2.4).
constexpr DriveMode kSmsmbModes[] = {
    {0, Drive::Position}, {1, Drive::Velocity}, {3, Drive::Position}, {4, Drive::Step}};

constexpr std::string_view kStsMotionFields[] = {"operating_mode", "torque_enable", "goal_position", "goal_time",
                                                 "goal_speed"};
constexpr std::string_view kSms1MotionFields[] = {"operating_mode", "torque_switch", "goal_position", "run_time",
                                                  "run_speed"};
// d55d: both angle limits 0 select wheel mode; releasing the brake or waking the motor resumes
// the goal it holds; homing turns the motor.
constexpr std::string_view kD55dMotionFields[] = {
    "cw_angle_limit", "ccw_angle_limit", "goal_position", "run_speed", "brake", "sleep", "photo_switch_homing"};
// scs has no mode byte: both angle limits 0 select the open-loop motor (SCSCL SDK PWMMode).
constexpr DriveMode kScsLimitsZeroDrive[] = {{0, Drive::Pwm}};
constexpr std::string_view kScsMotionFields[] = {"min_angle_limit", "max_angle_limit", "torque_enable",
                                                 "goal_position",   "goal_time",       "goal_speed"};
constexpr std::string_view kSmsmbMotionFields[] = {"mode", "goal_position", "torque_switch", "running_speed"};

constexpr StoppingWrite kStsStops[] = {{"torque_enable", 0}};
constexpr StoppingWrite kSms1Stops[] = {{"torque_switch", 0}};
// d55d (docs/PROTOCOL.md §2.3): "a speed of 0 or a brake command stops it at once"; sleep lets go.
constexpr StoppingWrite kD55dStops[] = {{"run_speed", 0}, {"brake", 1}, {"sleep", 1}};
constexpr StoppingWrite kSmsmbStops[] = {{"torque_switch", 0}};
constexpr StoppingWrite kScsStops[] = {{"torque_enable", 0}};

// What lets each motor drive ("no jump on enable"). d55d has no torque switch: asleep (47 = 1) it
// is free, braked (43 = 1) it stands; woken or released it would resume the goal or speed it
// holds (docs/PROTOCOL.md §2.3). Its run speed 0 ("stop without torque") is a command, not a
// switch: in speed mode it is the speed asked for.
constexpr EnableField kStsEnables[] = {{"torque_enable", 1, "torque on"}};
constexpr EnableField kSms1Enables[] = {{"torque_switch", 1, "torque on"}};
constexpr EnableField kD55dEnables[] = {{"sleep", 0, "wake"}, {"brake", 0, "brake release"}};
constexpr EnableField kSmsmbEnables[] = {{"torque_switch", 1, "torque on"}};
constexpr EnableField kScsEnables[] = {{"torque_enable", 1, "torque on"}};

// The fastest braking each servo has (docs/SAFETY.md "Stop distance"): acceleration 0 is "no
// ramp" on sts, sms1 and SMSMB (their tables' notes: "0 = maximum"); d55d documents no such
// value, so its largest count, 254 (2540 °/s²), for both of its ramps.
constexpr RampField kFeetechStopRamp[] = {{"acceleration", 0}};
constexpr RampField kD55dStopRamp[] = {{"acceleration", tables::kByteMax}, {"deceleration", tables::kByteMax}};

constexpr std::array kMotionSpecs{
    MotionSpec{TableId::Sts,
               "operating_mode",
               kStsModes,
               "min_angle_limit",
               "max_angle_limit",
               "torque_enable",
               "goal_position",
               "goal_time",
               "goal_speed",
               "present_position",
               {"torque_enable", 0},
               kStsMotionFields,
               kStsStops,
               StopAction::Hold,
               kStsEnables,
               kFeetechStopRamp,
               "present_speed"},
    MotionSpec{TableId::Sms1,
               "operating_mode",
               kSms1Modes,
               "min_angle_limit",
               "max_angle_limit",
               "torque_switch",
               "goal_position",
               "run_time",
               "run_speed",
               "present_position",
               {"torque_switch", 0},
               kSms1MotionFields,
               kSms1Stops,
               StopAction::Hold,
               kSms1Enables,
               kFeetechStopRamp,
               "present_speed"},
    // d55d has no torque switch: run speed 0 is its own "stop without torque" (docs/PROTOCOL.md §2.3).
    MotionSpec{TableId::D55d,
               "",
               {},
               "cw_angle_limit",
               "ccw_angle_limit",
               "",
               "goal_position",
               "",
               "run_speed",
               "present_position",
               {"run_speed", 0},
               kD55dMotionFields,
               kD55dStops,
               StopAction::Hold,
               kD55dEnables,
               kD55dStopRamp,
               "present_speed"},
    MotionSpec{TableId::Smsmb,
               "mode",
               kSmsmbModes,
               "min_angle_limit",
               "max_angle_limit",
               "torque_switch",
               "goal_position",
               "",
               "running_speed",
               "present_position",
               {"torque_switch", 0},
               kSmsmbMotionFields,
               kSmsmbStops,
               StopAction::Hold,
               kSmsmbEnables,
               kFeetechStopRamp,
               "present_speed"},
    MotionSpec{TableId::Scs,
               "",
               kScsLimitsZeroDrive,
               "min_angle_limit",
               "max_angle_limit",
               "torque_enable",
               "goal_position",
               "goal_time",
               "goal_speed",
               "present_position",
               {"torque_enable", 0},
               kScsMotionFields,
               kScsStops,
               StopAction::Hold,
               kScsEnables,
               {},
               "present_speed"},
};

const FieldSpec& field_named(const MotionSpec& spec, std::string_view name) {
  const FieldSpec* field = field_by_name(table(spec.table), name);
  if (field == nullptr) {
    throw std::logic_error("motion spec of table " + std::string(table(spec.table).name) + " names field '" +
                           std::string(name) + "', which the table does not have");
  }
  return *field;
}

std::uint16_t span_of(const MotionSpec& spec, const FieldSpec& field) {
  return address_span(table(spec.table).addressing, field);
}

// The byte offset of `field` inside data read from `range`, or nullopt when it is not inside.
std::optional<std::size_t> offset_in(const MotionSpec& spec, const BusRange& range, const FieldSpec& field) {
  if (field.addr < range.address || field.addr + span_of(spec, field) > range.end()) return std::nullopt;
  return std::size_t{static_cast<std::size_t>(field.addr - range.address)} *
         bytes_per_address(table(spec.table).addressing);
}

// Register tables are high byte first whatever the unit says; packet tables use `order`.
ByteOrder field_order(const MotionSpec& spec, ByteOrder order) {
  return table(spec.table).addressing == Addressing::Register ? ByteOrder::HighFirst : order;
}

std::optional<std::uint32_t> read_raw(const MotionSpec& spec, ByteOrder order, const StopContext& context,
                                      std::string_view name) {
  const FieldSpec& field = field_named(spec, name);
  for (std::size_t i = 0; i < context.ranges.size() && i < context.data.size(); ++i) {
    const auto offset = offset_in(spec, context.ranges[i], field);
    if (!offset || *offset + field.size > context.data[i].size()) continue;
    return load_raw(std::span(context.data[i]).subspan(*offset, field.size), field.size, field_order(spec, order));
  }
  return std::nullopt;
}

Expected<Drive> drive_of(const MotionSpec& spec, ByteOrder order, const StopContext& context) {
  if (spec.mode.empty()) {
    const auto min = read_raw(spec, order, context, spec.min_limit);
    const auto max = read_raw(spec, order, context, spec.max_limit);
    if (!min || !max) return unexpected(std::string("the angle limits were not read"));
    const Drive limits_zero = spec.modes.empty() ? Drive::Velocity : spec.modes.front().drive;
    return (*min == 0 && *max == 0) ? limits_zero : Drive::Position;
  }
  const auto mode = read_raw(spec, order, context, spec.mode);
  if (!mode) return unexpected(std::string("the operating mode was not read"));
  for (const DriveMode& entry : spec.modes) {
    if (entry.value == static_cast<std::int32_t>(*mode)) return entry.drive;
  }
  return unexpected("operating mode " + std::to_string(*mode) + " is not one this table documents");
}

BusWrite single_field_write(const MotionSpec& spec, ByteOrder order, const StoppingWrite& write) {
  const FieldSpec& field = field_named(spec, write.field);
  const auto raw = encode_value(field, write.value);
  if (!raw) throw std::logic_error("stopping value out of range for " + std::string(write.field));
  protocol::Bytes data(field.size, 0);
  store_raw(data, field.size, field_order(spec, order), *raw);
  return BusWrite{field.addr, std::move(data)};
}

}  // namespace

std::string_view to_string(StopAction action) {
  switch (action) {
    case StopAction::Hold: return "hold";
    case StopAction::TorqueOff: return "torque_off";
    case StopAction::None: return "none";
  }
  return "?";
}

const MotionSpec& motion_spec(TableId id) {
  for (const MotionSpec& spec : kMotionSpecs) {
    if (spec.table == id) return spec;
  }
  throw std::logic_error("no motion spec for table " + std::string(table(id).name));
}

BusRange goal_block(const MotionSpec& spec) {
  const FieldSpec& goal = field_named(spec, spec.goal_position);
  std::uint32_t begin = goal.addr;
  std::uint32_t end = goal.addr + span_of(spec, goal);
  const auto cover = [&](std::string_view name) {
    const FieldSpec& field = field_named(spec, name);
    begin = std::min<std::uint32_t>(begin, field.addr);
    end = std::max<std::uint32_t>(end, field.addr + span_of(spec, field));
  };
  cover(spec.goal_speed);
  if (!spec.goal_time.empty()) cover(spec.goal_time);
  for (const RampField& ramp : spec.stop_ramp) cover(ramp.field);
  return BusRange{static_cast<std::uint16_t>(begin), static_cast<std::uint16_t>(end - begin)};
}

double run_on(const MotionSpec& spec, std::int32_t speed, std::int32_t deceleration, std::int32_t resolution,
              double lead_seconds) {
  const TimedMoveSpec* units = timed_move_spec(spec.table);
  if (units == nullptr) return 0;
  const TimedMoveSpec scaled = at_resolution(*units, resolution);
  const double velocity = std::abs(speed * scaled.speed_unit);                                    // position units/s
  const double braking = spec.stop_ramp.empty() ? 0.0 : deceleration * scaled.acceleration_unit;  // units/s²
  return velocity * std::max(0.0, lead_seconds) + (braking > 0 ? velocity * velocity / (2.0 * braking) : 0.0);
}

std::optional<std::string> check_stop_deceleration(const MotionSpec& spec, std::int32_t count) {
  if (spec.stop_ramp.empty()) {
    return "table " + std::string(table(spec.table).name) +
           " has no acceleration field: its servos change speed at once, and a stop ramp cannot be set";
  }
  for (const RampField& ramp : spec.stop_ramp) {
    const FieldSpec& field = field_named(spec, ramp.field);
    if (count < 1 || count > field.max) {
      return "table " + std::string(table(spec.table).name) + " takes 1.." + std::to_string(field.max) + " (" +
             std::string(ramp.field) + ", " + std::string(field.unit) + "), not " + std::to_string(count);
    }
  }
  return std::nullopt;
}

namespace {

// The goal block's bytes in `context`; empty when it was not read whole.
protocol::Bytes goal_block_as_read(const MotionSpec& spec, const StopContext& context) {
  const BusRange block = goal_block(spec);
  const std::size_t per = bytes_per_address(table(spec.table).addressing);
  for (std::size_t i = 0; i < context.ranges.size() && i < context.data.size(); ++i) {
    if (!context.ranges[i].contains(block)) continue;
    const std::size_t offset = std::size_t{static_cast<std::size_t>(block.address - context.ranges[i].address)} * per;
    if (offset + block.count * per > context.data[i].size()) return {};
    return protocol::Bytes(context.data[i].begin() + static_cast<std::ptrdiff_t>(offset),
                           context.data[i].begin() + static_cast<std::ptrdiff_t>(offset + block.count * per));
  }
  return {};
}

// The ranges holding the stop context's fields and `extra` fields, merged where they lie close.
std::vector<BusRange> context_reads(const MotionSpec& spec, std::span<const EnableField> extra) {
  std::vector<BusRange> needed;
  const auto add_field = [&](std::string_view name) {
    if (name.empty()) return;
    const FieldSpec& field = field_named(spec, name);
    needed.push_back(BusRange{field.addr, span_of(spec, field)});
  };
  for (const std::string_view name : drive_fields(spec)) add_field(name);
  add_field(spec.torque);
  needed.push_back(goal_block(spec));
  add_field(spec.present_position);
  // The run-on: the present speed, and d55d's angle resolution (its units).
  add_field(spec.present_speed);
  if (const TimedMoveSpec* units = timed_move_spec(spec.table)) add_field(units->resolution);
  for (const EnableField& enable : extra) add_field(enable.field);
  std::sort(needed.begin(), needed.end(), [](const BusRange& a, const BusRange& b) { return a.address < b.address; });

  // Merge ranges whose gap is small: one longer READ costs less than another transaction
  // (a request and a reply header are about 10 bytes on the wire, and the servo's return delay
  // and the gateway's turnaround come on top): d55d's limits, resolution and goal block in one.
  constexpr std::uint32_t kMergeGap = 24;
  std::vector<BusRange> merged;
  for (const BusRange& range : needed) {
    if (!merged.empty() && range.address <= merged.back().end() + kMergeGap) {
      const std::uint32_t end = std::max(merged.back().end(), range.end());
      merged.back().count = static_cast<std::uint16_t>(end - merged.back().address);
    } else {
      merged.push_back(range);
    }
  }
  return merged;
}

}  // namespace

std::vector<BusRange> stop_context_reads(const MotionSpec& spec) { return context_reads(spec, {}); }

Expected<SafeStopPlan> plan_safe_stop(const MotionSpec& spec, StopAction action, ByteOrder order,
                                      const StopContext& context, const StopOptions& options) {
  SafeStopPlan plan;
  if (action == StopAction::None) {
    plan.what = "none (configured)";
    return plan;
  }
  const auto drive = drive_of(spec, order, context);
  if (!drive) return unexpected(drive.error());
  plan.drive = *drive;
  if (!spec.torque.empty() && !options.torque_known_on) {
    const auto torque = read_raw(spec, order, context, spec.torque);
    if (!torque) return unexpected(std::string("the torque switch was not read"));
    if (*torque == 0) {
      // A motor without torque is not driving; a goal write would switch it on (STS firmware).
      plan.what = "nothing to do (torque already off)";
      return plan;
    }
  }
  if (action == StopAction::TorqueOff || plan.drive == Drive::Step) {
    plan.writes.push_back(single_field_write(spec, order, spec.torque_off));
    plan.what = action == StopAction::TorqueOff
                    ? std::string("torque off")
                    : std::string("torque off (step mode: every goal is relative to the running target, none holds)");
    return plan;
  }

  // Hold: the goal block as read, with the stop ramp and the one field that stops this drive
  // changed. The block is written whole, so the ramp goes in the same frame as the goal.
  const BusRange block = goal_block(spec);
  protocol::Bytes data = goal_block_as_read(spec, context);
  if (data.empty()) return unexpected(std::string("the goal block was not read"));
  const auto set_raw = [&](std::string_view name, std::uint32_t raw) {
    const FieldSpec& field = field_named(spec, name);
    const std::size_t offset = std::size_t{static_cast<std::size_t>(field.addr - block.address)} *
                               bytes_per_address(table(spec.table).addressing);
    store_raw(std::span(data).subspan(offset, field.size), field.size, field_order(spec, order), raw);
  };
  std::string ramp_text;  // ", acceleration := 0"
  std::optional<std::int32_t> ramp_count;
  if (!options.keep_ramp) {
    for (const RampField& ramp : spec.stop_ramp) {
      const std::int32_t count = options.deceleration.value_or(ramp.fastest);
      const auto raw = encode_value(field_named(spec, ramp.field), count);
      if (!raw) return unexpected("stop ramp " + std::to_string(count) + " is outside " + std::string(ramp.field));
      set_raw(ramp.field, *raw);
      ramp_text += ", " + std::string(ramp.field) + " := " + std::to_string(count);
      ramp_count = count;
    }
  }
  switch (plan.drive) {
    case Drive::Position: {
      const FieldSpec& present = field_named(spec, spec.present_position);
      const auto raw = read_raw(spec, order, context, spec.present_position);
      if (!raw) return unexpected(std::string("the present position was not read"));
      const std::int32_t position = decode_value(present, *raw);
      // Where the axis will stand: on by what it covers while the frame is on its way, then braked
      // at the ramp just set (none on Feetech tables at their fastest). A goal behind it would be
      // driven back to.
      std::int64_t goal = position;
      if (!options.keep_ramp && !spec.present_speed.empty()) {
        const auto speed = read_raw(spec, order, context, spec.present_speed);
        const TimedMoveSpec* units = timed_move_spec(spec.table);
        std::int32_t resolution = 0;
        if (units != nullptr && !units->resolution.empty()) {
          const auto read = read_raw(spec, order, context, units->resolution);
          if (!read) return unexpected(std::string(units->resolution) + " was not read");
          resolution = std::max<std::int32_t>(1, static_cast<std::int32_t>(*read));
        }
        if (!speed) return unexpected(std::string("the present speed was not read"));
        const std::int32_t velocity = decode_value(field_named(spec, spec.present_speed), *speed);
        // Up to the next whole unit: a goal a fraction of a step behind the axis is still behind it.
        const auto ahead = static_cast<std::int64_t>(
            std::ceil(run_on(spec, velocity, ramp_count.value_or(0), resolution, options.lead_seconds)));
        goal += velocity < 0 ? -ahead : ahead;
      }
      // Inside the axis's angle limits where it has them, and inside what the goal field holds.
      const auto min_limit = read_raw(spec, order, context, spec.min_limit);
      const auto max_limit = read_raw(spec, order, context, spec.max_limit);
      if (goal != position && min_limit && max_limit && *max_limit > *min_limit) {
        const FieldSpec& min_field = field_named(spec, spec.min_limit);
        const FieldSpec& max_field = field_named(spec, spec.max_limit);
        goal = std::clamp<std::int64_t>(goal, decode_value(min_field, *min_limit), decode_value(max_field, *max_limit));
      }
      const FieldSpec& goal_field = field_named(spec, spec.goal_position);
      goal = std::clamp<std::int64_t>(goal, goal_field.min, goal_field.max);
      if (goal == position) {
        // The present position's bytes become the goal's: both fields share size and encoding.
        set_raw(spec.goal_position, *raw);
      } else {
        set_raw(spec.goal_position, encode_value(goal_field, static_cast<std::int32_t>(goal)).value_or(*raw));
      }
      plan.what = "hold (position mode: goal := present position " + std::to_string(position) +
                  (goal == position ? std::string()
                                    : " + run-on " + std::to_string(goal - position) + " = " + std::to_string(goal)) +
                  ramp_text + ")";
      break;
    }
    case Drive::Velocity:
      set_raw(spec.goal_speed, 0);
      plan.what = "hold (speed mode: speed := 0" + ramp_text + ")";
      break;
    case Drive::Pwm:
      if (spec.goal_time.empty()) return unexpected(std::string("PWM mode without a PWM field"));
      set_raw(spec.goal_time, 0);
      plan.what = "hold (PWM mode: duty := 0" + ramp_text + ")";
      break;
    case Drive::Step: break;  // handled above
  }
  plan.writes.push_back(BusWrite{block.address, std::move(data)});
  return plan;
}

BusWrite torque_off_write(const MotionSpec& spec, ByteOrder order) {
  return single_field_write(spec, order, spec.torque_off);
}

bool is_motion_field(const MotionSpec& spec, std::string_view field) {
  return std::find(spec.motion_fields.begin(), spec.motion_fields.end(), field) != spec.motion_fields.end();
}

namespace {

// The raw value a write puts into `field`, or nullopt when the write does not cover all of it.
std::optional<std::uint32_t> written_raw(const MotionSpec& spec, ByteOrder order, const BusWrite& write,
                                         const FieldSpec& field) {
  const std::size_t per = bytes_per_address(table(spec.table).addressing);
  const BusRange range{write.address, static_cast<std::uint16_t>(write.data.size() / per)};
  const auto offset = offset_in(spec, range, field);
  if (!offset || *offset + field.size > write.data.size()) return std::nullopt;
  return load_raw(std::span(write.data).subspan(*offset, field.size), field.size, field_order(spec, order));
}

bool overlaps(const MotionSpec& spec, const BusWrite& write, const FieldSpec& field) {
  const std::size_t per = bytes_per_address(table(spec.table).addressing);
  const std::uint32_t end = write.address + static_cast<std::uint32_t>(write.data.size() / per);
  return field.addr < end && field.addr + span_of(spec, field) > write.address;
}

}  // namespace

std::optional<std::string> motion_in_plan(const MotionSpec& spec, ByteOrder order, const WritePlan& plan) {
  for (const BusWrite& write : plan.writes) {
    for (const std::string_view name : spec.motion_fields) {
      const FieldSpec& field = field_named(spec, name);
      if (!overlaps(spec, write, field)) continue;
      const auto raw = written_raw(spec, order, write, field);
      const bool stopping =
          raw && std::any_of(spec.stopping_writes.begin(), spec.stopping_writes.end(), [&](const StoppingWrite& stop) {
            return stop.field == name && encode_value(field, stop.value) == raw;
          });
      if (!stopping) return std::string(name) + " (" + std::to_string(field.addr) + ")";
    }
  }
  return std::nullopt;
}

std::string_view to_string(Drive drive) {
  switch (drive) {
    case Drive::Position: return "position mode";
    case Drive::Velocity: return "speed mode";
    case Drive::Pwm: return "PWM mode";
    case Drive::Step: return "step mode";
  }
  return "?";
}

std::vector<std::string_view> drive_fields(const MotionSpec& spec) {
  if (!spec.mode.empty()) return {spec.mode};
  return {spec.min_limit, spec.max_limit};
}

namespace {

// Whether `writes` put an enable field's `on` value.
bool writes_enabling_value(const MotionSpec& spec, ByteOrder order, std::span<const BusWrite> writes) {
  return std::any_of(writes.begin(), writes.end(), [&](const BusWrite& write) {
    return std::any_of(spec.enables.begin(), spec.enables.end(), [&](const EnableField& enable) {
      const FieldSpec& field = field_named(spec, enable.field);
      const auto raw = written_raw(spec, order, write, field);
      return raw && raw == encode_value(field, enable.on);
    });
  });
}

}  // namespace

bool may_enable_motion(const MotionSpec& spec, ByteOrder order, std::span<const BusWrite> writes) {
  const auto drive = drive_fields(spec);
  return writes_enabling_value(spec, order, writes) ||
         std::any_of(writes.begin(), writes.end(), [&](const BusWrite& write) {
           return std::any_of(drive.begin(), drive.end(),
                              [&](std::string_view name) { return overlaps(spec, write, field_named(spec, name)); });
         });
}

std::vector<BusRange> enable_context_reads(const MotionSpec& spec) { return context_reads(spec, spec.enables); }

std::optional<bool> motion_enabled(const MotionSpec& spec, ByteOrder order, const StopContext& context) {
  bool enabled = true;
  for (const EnableField& enable : spec.enables) {
    const FieldSpec& field = field_named(spec, enable.field);
    const auto raw = read_raw(spec, order, context, enable.field);
    if (!raw) return std::nullopt;
    enabled = enabled && raw == encode_value(field, enable.on);
  }
  return enabled;
}

namespace {

// The context as it will be once `writes` are carried out: their bytes laid over the bytes read.
std::vector<protocol::Bytes> after_writes(const MotionSpec& spec, const StopContext& context,
                                          std::span<const BusWrite> writes) {
  const std::size_t per = bytes_per_address(table(spec.table).addressing);
  std::vector<protocol::Bytes> data(context.data.begin(), context.data.end());
  for (std::size_t i = 0; i < context.ranges.size() && i < data.size(); ++i) {
    const BusRange& range = context.ranges[i];
    for (const BusWrite& write : writes) {
      for (std::size_t byte = 0; byte < write.data.size(); ++byte) {
        const std::uint32_t address = write.address + static_cast<std::uint32_t>(byte / per);
        if (address < range.address || address >= range.end()) continue;
        const std::size_t offset = std::size_t{address - range.address} * per + byte % per;
        if (offset < data[i].size()) data[i][offset] = write.data[byte];
      }
    }
  }
  return data;
}

// Before a drive change: the goal block as read with goal := present position and the speed and
// duty fields 0, so that it holds in the old drive and leaves nothing stale for the new one.
Expected<SafeStopPlan> neutral_block(const MotionSpec& spec, ByteOrder order, const StopContext& context) {
  const BusRange block = goal_block(spec);
  const std::size_t per = bytes_per_address(table(spec.table).addressing);
  protocol::Bytes data = goal_block_as_read(spec, context);
  const auto present = read_raw(spec, order, context, spec.present_position);
  if (data.empty() || !present) return unexpected(std::string("the goal block or the present position was not read"));
  const auto set_raw = [&](std::string_view name, std::uint32_t raw) {
    const FieldSpec& field = field_named(spec, name);
    const std::size_t offset = std::size_t{static_cast<std::size_t>(field.addr - block.address)} * per;
    store_raw(std::span(data).subspan(offset, field.size), field.size, field_order(spec, order), raw);
  };
  set_raw(spec.goal_position, *present);
  set_raw(spec.goal_speed, 0);
  if (!spec.goal_time.empty()) set_raw(spec.goal_time, 0);
  SafeStopPlan plan;
  plan.what = "goal := present position " +
              std::to_string(decode_value(field_named(spec, spec.present_position), *present)) + ", " +
              std::string(spec.goal_speed) + " := 0" +
              (spec.goal_time.empty() ? std::string() : ", " + std::string(spec.goal_time) + " := 0");
  plan.writes.push_back(BusWrite{block.address, std::move(data)});
  return plan;
}

}  // namespace

Expected<std::optional<SafeStopPlan>> plan_enable_hold(const MotionSpec& spec, ByteOrder order,
                                                       const StopContext& context, std::span<const BusWrite> writes) {
  const std::vector<protocol::Bytes> after_data = after_writes(spec, context, writes);
  const StopContext after{context.ranges, after_data};
  const auto enabled_before = motion_enabled(spec, order, context);
  const auto enabled_after = motion_enabled(spec, order, after);
  if (!enabled_before || !enabled_after) return unexpected(std::string("the enable fields were not read"));
  if (!*enabled_after) return std::optional<SafeStopPlan>();  // nothing can move
  const auto drive_before = drive_of(spec, order, context);
  if (!drive_before) return unexpected(drive_before.error());
  const auto drive_after = drive_of(spec, order, after);
  if (!drive_after) return unexpected(drive_after.error());

  if (*drive_before == *drive_after) {
    // Enabled in its drive: a hold would cancel the move under way. In step mode every goal is
    // relative to the running target: none is stale.
    if (*enabled_before || *drive_after == Drive::Step) return std::optional<SafeStopPlan>();
    // The motor stands: the hold keeps the PLC's ramp (a stop's fastest ramp would outlive it).
    auto hold = plan_safe_stop(spec, StopAction::Hold, order, context,
                               StopOptions{.torque_known_on = true, .deceleration = std::nullopt, .keep_ramp = true});
    if (!hold) return unexpected(hold.error());
    std::string enabled;  // what the writes switch on: "torque on", "wake, brake release"
    for (const EnableField& enable : spec.enables) {
      const FieldSpec& field = field_named(spec, enable.field);
      if (read_raw(spec, order, context, enable.field) == encode_value(field, enable.on)) continue;
      enabled += (enabled.empty() ? "" : ", ") + std::string(enable.what);
    }
    hold->what = enabled + ": " + hold->what;
    return std::optional<SafeStopPlan>(std::move(*hold));
  }
  const std::string change = std::string(to_string(*drive_before)) + " -> " + std::string(to_string(*drive_after));
  if (*drive_before == Drive::Step) {
    // A goal written in step mode is a move; the torque off that stops it there would be undone
    // by a request that enables the motor itself.
    if (writes_enabling_value(spec, order, writes)) {
      return unexpected("the write leaves step mode and enables the motor at once (" + change +
                        "): no hold is safe in both drives; write the mode first, then enable");
    }
    SafeStopPlan off;
    off.drive = *drive_before;
    off.writes.push_back(torque_off_write(spec, order));
    off.what = "drive change (" + change + "): torque off first (no goal holds in step mode)";
    return std::optional<SafeStopPlan>(std::move(off));
  }
  // Enabled into step mode: no goal is stale there, as above.
  if (!*enabled_before && *drive_after == Drive::Step) return std::optional<SafeStopPlan>();
  auto neutral = neutral_block(spec, order, context);
  if (!neutral) return unexpected(neutral.error());
  neutral->drive = *drive_before;
  neutral->what = "drive change (" + change + "): " + neutral->what;
  return std::optional<SafeStopPlan>(std::move(*neutral));
}

}  // namespace sms::modbus_map
