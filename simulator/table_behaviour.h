#pragma once
// What the simulator needs to know about a table beyond its layout: which field plays which
// part in the servo's behaviour (looked up by the modbus_map field name, so the layout stays
// in one place), the physical units, and the firmware's instruction set. Data only.
#include <cstdint>
#include <span>
#include <string_view>

#include "modbus_map/control_table.h"

namespace sms::simulator {

enum class Role : std::uint8_t {
  FirmwareMajor,
  FirmwareMinor,
  ModelMajor,
  ModelMinor,
  Id,
  BaudCode,
  ReturnDelay,
  ResponseLevel,
  MinLimit,  // d55d: CW angle limit
  MaxLimit,  // d55d: CCW angle limit
  MaxTemperature,
  MaxVoltage,
  MinVoltage,
  MaxTorque,
  UnloadConditions,
  AngleResolution,
  PositionOffset,
  Mode,
  TorqueEnable,
  Acceleration,
  Deceleration,
  GoalPosition,
  GoalTime,  // sts/sms1: PWM magnitude in mode 2 (sign bit 10); sms1: move time in mode 0
  GoalSpeed,
  TorqueLimit,
  Lock,
  FaultReset,
  PresentPosition,
  PresentSpeed,
  PresentLoad,
  PresentVoltage,
  PresentTemperature,
  Status,
  Moving,
  PresentGoal,
  PresentCurrent,
  RegWriteFlag,
  AccumulatedAngle,
  Brake,
  Sleep,
  Heartbeat,
  HomingDirection,
  Homing,
  ClearUnload,
  PhotoSwitchState,
  Phase,  // sts: bit 2 selects the speed unit
  Count,
};

// How the servo drives its motor (docs/PROTOCOL.md §2: operating modes).
enum class ControlMode : std::uint8_t {
  Position,         // goal position within the angle limits; multi-turn when both are 0
  Velocity,         // constant speed, the goal speed's sign is the direction
  Pwm,              // open loop: goal time is the signed duty cycle, 0.1 %
  Step,             // each goal position written is a relative move, no limits
  PositionRelease,  // SMSMB mode 3: position servo that lets go of the torque on arrival
};

struct RoleBinding {
  Role role;
  std::string_view field;  // modbus_map FieldSpec::name
};
struct ModeBinding {
  std::int32_t value;  // the mode field's value
  ControlMode mode;
};
// Power-on values the simulated servo uses where the table gives no default (identity
// fields, a d55d motor's travel).
struct SimulatedDefault {
  Role role;
  std::int32_t value;
};

struct TableBehaviour {
  modbus_map::TableId table;
  std::span<const RoleBinding> roles;
  // Empty: position mode, `limits_zero_mode` when both angle limits are 0.
  std::span<const ModeBinding> modes;
  ControlMode limits_zero_mode;                // d55d: wheel (velocity); scs: open-loop motor (PWM)
  std::span<const std::uint8_t> instructions;  // packet instruction codes the firmware knows
  std::span<const SimulatedDefault> simulated_defaults;

  double return_delay_us_per_unit;
  std::int32_t return_delay_floor;      // smaller values act as this one (sts: 50 = 100 µs); 0: none
  double degrees_per_position_unit;     // 0: angle-resolution field × 0.1° (d55d)
  double degrees_per_s_per_speed_unit;  // 0: one position unit per second (d55d)
  // When not 0: the phase byte bit that switches the speed unit to one position unit per
  // second (sts phase bit 2: 0 = 0.732 rpm, 1 = 1 step/s; Feetech wiki memory-sts).
  std::uint8_t phase_bit_speed_in_steps;
  double degrees_per_s2_per_accel_unit;  // acceleration field unit; unused without the role
  double top_speed_degrees_per_s;        // what goal speed 0 ("maximum") means
  std::int32_t steps_per_turn;           // single-turn positions wrap at this; 0: no wrap
  std::int32_t centre_position;          // mid-point calibration target (2048)
  std::int32_t power_on_position;

  // ERROR / status bits (docs/PROTOCOL.md §1.1, §1.2, §2.4)
  std::uint8_t refused_bit;   // WRITE to a read-only field, bad range, unknown instruction
  std::uint8_t checksum_bit;  // 0: the protocol has none
  std::uint8_t temperature_bit;
  std::uint8_t overvoltage_bit;
  std::uint8_t error_mask;            // bits that are errors (SMSMB status bit 4 is "torque on")
  std::uint8_t torque_on_status_bit;  // 0: none

  // Feetech response level: 0 = READ and PING only. d55d: 0 none, 1 READ, 2 all.
  bool d55d_response_levels;
  bool speed_zero_stops;             // d55d: run speed 0 = stop without torque
  bool move_time_in_position_mode;   // sms1: run time (ms) when run speed is 0
  bool torque_128_calibrates;        // writing 128 to torque enable = mid-point calibration
  std::uint16_t factory_area_start;  // SMSMB: fields from here are writable only after lock 128
};

const TableBehaviour& behaviour(modbus_map::TableId table);

}  // namespace sms::simulator
