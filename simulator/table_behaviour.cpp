#include "simulator/table_behaviour.h"

#include <array>

#include "protocol/d55d.h"
#include "protocol/feetech.h"

namespace sms::simulator {
namespace {

using modbus_map::TableId;
namespace common = protocol::common;
namespace feetech = protocol::feetech;
namespace d55d = protocol::d55d;

constexpr double kDegreesPerStep = 360.0 / 4096.0;
// SM40BL: 65 rpm at 12 V (doc 001 §15); what "goal speed 0 = maximum" runs at.
constexpr double kFeetechTopSpeed = 65.0 * 360.0 / 60.0;
// Feetech's speed unit 0.732 rpm (≈ 50 steps/s), the factory unit of STS/SMS (wiki memory-sts,
// FTServo_Python examples) and SMSMB.
constexpr double kDegreesPerSPer0732Rpm = 0.732 * 360.0 / 60.0;
// SCS: 1024 steps over 300°; the SCSCL SDK examples run at 1500 steps/s "maximum speed".
constexpr double kScsDegreesPerStep = 300.0 / 1024.0;
constexpr double kScsTopSpeed = 1500.0 * kScsDegreesPerStep;

// --- sts (docs/PROTOCOL.md §2.1) ---------------------------------------------------------------------
constexpr RoleBinding kStsRoles[] = {
    {Role::FirmwareMajor, "firmware_major"},
    {Role::FirmwareMinor, "firmware_minor"},
    {Role::ModelMajor, "model_major"},
    {Role::ModelMinor, "model_minor"},
    {Role::Id, "id"},
    {Role::BaudCode, "baud_rate"},
    {Role::ReturnDelay, "return_delay"},
    {Role::ResponseLevel, "response_level"},
    {Role::MinLimit, "min_angle_limit"},
    {Role::MaxLimit, "max_angle_limit"},
    {Role::MaxTemperature, "max_temperature"},
    {Role::MaxVoltage, "max_input_voltage"},
    {Role::MinVoltage, "min_input_voltage"},
    {Role::MaxTorque, "max_torque"},
    {Role::UnloadConditions, "unload_conditions"},
    {Role::PositionOffset, "position_offset"},
    {Role::Mode, "operating_mode"},
    {Role::TorqueEnable, "torque_enable"},
    {Role::Acceleration, "acceleration"},
    {Role::GoalPosition, "goal_position"},
    {Role::GoalTime, "goal_time"},
    {Role::GoalSpeed, "goal_speed"},
    {Role::TorqueLimit, "torque_limit"},
    {Role::Lock, "lock"},
    {Role::PresentPosition, "present_position"},
    {Role::PresentSpeed, "present_speed"},
    {Role::PresentLoad, "present_load"},
    {Role::PresentVoltage, "present_voltage"},
    {Role::PresentTemperature, "present_temperature"},
    {Role::RegWriteFlag, "reg_write_flag"},
    {Role::Status, "status"},
    {Role::Moving, "moving"},
    {Role::PresentGoal, "present_goal_position"},
    {Role::PresentCurrent, "present_current"},
    {Role::Phase, "phase"},
};
constexpr ModeBinding kStsModes[] = {
    {0, ControlMode::Position},
    {1, ControlMode::Velocity},
    {2, ControlMode::Pwm},
    {3, ControlMode::Step},
};
constexpr std::uint8_t kStsInstructions[] = {
    common::kPing,         common::kRead,       common::kWrite,     common::kRegWrite,
    common::kAction,       feetech::kRecovery,  feetech::kReboot,   feetech::kBackup,
    feetech::kResetStatus, feetech::kCalibrate, feetech::kSyncRead, common::kSyncWrite,
};
// The FD tool's SM40BL/STS3215 readout in doc 001 §15: firmware 2.48, servo 8.42.
constexpr SimulatedDefault kStsIdentity[] = {
    {Role::FirmwareMajor, 2},
    {Role::FirmwareMinor, 48},
    {Role::ModelMajor, 8},
    {Role::ModelMinor, 42},
};

// --- sms1 (docs/PROTOCOL.md §2.2) --------------------------------------------------------------------
constexpr RoleBinding kSms1Roles[] = {
    {Role::FirmwareMajor, "software_version"},
    {Role::Id, "id"},
    {Role::BaudCode, "baud_rate"},
    {Role::ReturnDelay, "return_delay"},
    {Role::ResponseLevel, "response_level"},
    {Role::MinLimit, "min_angle_limit"},
    {Role::MaxLimit, "max_angle_limit"},
    {Role::MaxTemperature, "max_temperature"},
    {Role::MaxVoltage, "max_input_voltage"},
    {Role::MinVoltage, "min_input_voltage"},
    {Role::MaxTorque, "max_torque"},
    {Role::UnloadConditions, "unload_conditions"},
    {Role::PositionOffset, "position_correction"},
    {Role::Mode, "operating_mode"},
    {Role::TorqueEnable, "torque_switch"},
    {Role::Acceleration, "acceleration"},
    {Role::GoalPosition, "goal_position"},
    {Role::GoalTime, "run_time"},
    {Role::GoalSpeed, "run_speed"},
    {Role::Lock, "lock"},
    {Role::PresentPosition, "present_position"},
    {Role::PresentSpeed, "present_speed"},
    {Role::PresentLoad, "present_load"},
    {Role::PresentVoltage, "present_voltage"},
    {Role::PresentTemperature, "present_temperature"},
    {Role::RegWriteFlag, "reg_write_flag"},
    {Role::Status, "error"},
    {Role::Moving, "moving"},
    {Role::PresentGoal, "present_goal_position"},
    {Role::PresentCurrent, "present_current"},
};
constexpr ModeBinding kSms1Modes[] = {
    {0, ControlMode::Position},
    {1, ControlMode::Velocity},
    {2, ControlMode::Pwm},
};
// SMS 1.0 (2016) predates REBOOT, BACKUP, RECOVERY, RESET STATUS and CALIBRATE ("newer
// firmware", docs/PROTOCOL.md §1.1); SYNC READ is STS/SMS.
constexpr std::uint8_t kSms1Instructions[] = {
    common::kPing,   common::kRead,      common::kWrite,     common::kRegWrite,
    common::kAction, feetech::kSyncRead, common::kSyncWrite,
};
constexpr SimulatedDefault kSms1Identity[] = {
    {Role::FirmwareMajor, 0x0101},  // V1.01, the document's revision
};

// --- scs (Feetech SCSCL SDK) -------------------------------------------------------------
constexpr RoleBinding kScsRoles[] = {
    {Role::FirmwareMajor, "firmware_major"},
    {Role::FirmwareMinor, "firmware_minor"},
    {Role::ModelMajor, "model_major"},
    {Role::ModelMinor, "model_minor"},
    {Role::Id, "id"},
    {Role::BaudCode, "baud_rate"},
    {Role::ReturnDelay, "return_delay"},
    {Role::ResponseLevel, "response_level"},
    {Role::MinLimit, "min_angle_limit"},
    {Role::MaxLimit, "max_angle_limit"},
    {Role::MaxTemperature, "max_temperature"},
    {Role::MaxVoltage, "max_input_voltage"},
    {Role::MinVoltage, "min_input_voltage"},
    {Role::UnloadConditions, "unload_conditions"},
    {Role::TorqueEnable, "torque_enable"},
    {Role::GoalPosition, "goal_position"},
    {Role::GoalTime, "goal_time"},
    {Role::GoalSpeed, "goal_speed"},
    {Role::Lock, "lock"},
    {Role::PresentPosition, "present_position"},
    {Role::PresentSpeed, "present_speed"},
    {Role::PresentLoad, "present_load"},
    {Role::PresentVoltage, "present_voltage"},
    {Role::PresentTemperature, "present_temperature"},
    {Role::RegWriteFlag, "reg_write_flag"},
    {Role::Status, "status"},
    {Role::Moving, "moving"},
    {Role::PresentCurrent, "present_current"},
};
// The SCSCL SDK uses PING, READ, WRITE, REG WRITE, ACTION and SYNC WRITE; SYNC READ is STS/SMS
// only (docs/PROTOCOL.md §1.1) and the newer instructions (REBOOT, BACKUP, CALIBRATE, ...) are STS firmware.
constexpr std::uint8_t kScsInstructions[] = {
    common::kPing, common::kRead, common::kWrite, common::kRegWrite, common::kAction, common::kSyncWrite,
};
// SCS0009 as Feetech's SCSCL SDK reads it: model word 0x0504 high byte first at 3-4.
constexpr SimulatedDefault kScsIdentity[] = {
    {Role::FirmwareMajor, 1},
    {Role::FirmwareMinor, 0},
    {Role::ModelMajor, 5},
    {Role::ModelMinor, 4},
};

// --- d55d (docs/PROTOCOL.md §2.3) --------------------------------------------------------------------
constexpr RoleBinding kD55dRoles[] = {
    {Role::FirmwareMajor, "software_version"},
    {Role::ModelMajor, "vendor_code"},
    {Role::Id, "id"},
    {Role::BaudCode, "baud_rate"},
    {Role::ReturnDelay, "return_delay"},
    {Role::MinLimit, "cw_angle_limit"},
    {Role::MaxLimit, "ccw_angle_limit"},
    {Role::MaxTemperature, "max_temperature"},
    {Role::AngleResolution, "angle_resolution"},
    {Role::ResponseLevel, "response_level"},
    {Role::Heartbeat, "heartbeat_enable"},
    {Role::UnloadConditions, "unload_conditions"},
    {Role::HomingDirection, "photo_switch_zero_direction"},
    {Role::Homing, "photo_switch_homing"},
    {Role::ClearUnload, "clear_unload_condition"},
    {Role::GoalPosition, "goal_position"},
    {Role::GoalSpeed, "run_speed"},
    {Role::Acceleration, "acceleration"},
    {Role::Deceleration, "deceleration"},
    {Role::PresentPosition, "present_position"},
    {Role::PresentSpeed, "present_speed"},
    {Role::AccumulatedAngle, "accumulated_angle"},
    {Role::Moving, "moving"},
    {Role::Brake, "brake"},
    {Role::RegWriteFlag, "reg_write_flag"},
    {Role::PresentTemperature, "present_temperature"},
    {Role::Sleep, "sleep"},
    {Role::PhotoSwitchState, "photo_switch_state"},
};
constexpr std::uint8_t kD55dInstructions[] = {
    common::kPing,   common::kRead,          common::kWrite,          common::kRegWrite,  common::kAction, d55d::kReset,
    d55d::kStartEnd, d55d::kTrajectoryWrite, d55d::kTrajectoryAction, common::kSyncWrite, d55d::kCustom,
};
constexpr SimulatedDefault kD55dIdentity[] = {
    {Role::ModelMajor, 0x5D},
    {Role::FirmwareMajor, 1},
    // "max angle × resolution" (doc 002 §3.1): a 360° finger/wrist motor at the default
    // resolution of 1°. Without it both limits would be 0, which is wheel mode.
    {Role::MaxLimit, 360},
};

// --- smsmb (docs/PROTOCOL.md §2.4) -------------------------------------------------------------------
constexpr RoleBinding kSmsmbRoles[] = {
    {Role::FirmwareMajor, "firmware_version"},
    {Role::ModelMajor, "servo_version"},
    {Role::Id, "id"},
    {Role::BaudCode, "baud_rate"},
    {Role::ReturnDelay, "return_delay"},
    {Role::MinLimit, "min_angle_limit"},
    {Role::MaxLimit, "max_angle_limit"},
    {Role::PositionOffset, "position_calibration"},
    {Role::Mode, "mode"},
    {Role::GoalPosition, "goal_position"},
    {Role::TorqueEnable, "torque_switch"},
    {Role::Acceleration, "acceleration"},
    {Role::GoalSpeed, "running_speed"},
    {Role::TorqueLimit, "torque_limit"},
    {Role::Lock, "lock"},
    {Role::FaultReset, "fault_reset"},
    {Role::UnloadConditions, "unload_conditions"},
    {Role::MaxTemperature, "max_temperature"},
    {Role::MaxVoltage, "max_input_voltage"},
    {Role::MinVoltage, "min_input_voltage"},
    {Role::Status, "status"},
    {Role::PresentPosition, "present_position"},
    {Role::PresentSpeed, "present_speed"},
    {Role::PresentLoad, "output_pwm"},
    {Role::PresentVoltage, "present_voltage"},
    {Role::PresentTemperature, "present_temperature"},
    {Role::Moving, "moving"},
    {Role::PresentCurrent, "present_current"},
};
constexpr ModeBinding kSmsmbModes[] = {
    {0, ControlMode::Position},
    {1, ControlMode::Velocity},
    {3, ControlMode::PositionRelease},
    {4, ControlMode::Step},
};
constexpr SimulatedDefault kSmsmbIdentity[] = {
    {Role::FirmwareMajor, 3},
    {Role::ModelMajor, 9},
};

constexpr TableBehaviour kSts{
    .table = TableId::Sts,
    .roles = kStsRoles,
    .modes = kStsModes,
    .limits_zero_mode = ControlMode::Position,
    .instructions = kStsInstructions,
    .simulated_defaults = kStsIdentity,
    .return_delay_us_per_unit = 2.0,
    .return_delay_floor = 50,  // "below 50 acts as 50" (wiki memory-sts, address 7)
    .degrees_per_position_unit = kDegreesPerStep,
    .degrees_per_s_per_speed_unit = kDegreesPerSPer0732Rpm,  // phase bit 2 clear (factory)
    .phase_bit_speed_in_steps = 1 << 2,
    .degrees_per_s2_per_accel_unit = 100.0 * kDegreesPerStep,
    .top_speed_degrees_per_s = kFeetechTopSpeed,
    .steps_per_turn = 4096,
    .centre_position = 2048,
    .power_on_position = 2048,
    .refused_bit = 0,  // Feetech firmware flags no refused write (docs/DECISIONS.md, Vendor fidelity)
    .checksum_bit = 0,
    .temperature_bit = feetech::error_bit::kTemperature,
    .overvoltage_bit = feetech::error_bit::kVoltage,
    // Bit 4 is unused by current firmware (wiki memory-sts) but doc 001 names it "angle": a
    // fault injection may still set it, as an older firmware would.
    .error_mask = 0x3F,
    .torque_on_status_bit = 0,
    .d55d_response_levels = false,
    .speed_zero_stops = false,
    .move_time_in_position_mode = false,
    .torque_128_calibrates = true,
    .factory_area_start = 0,
};

constexpr TableBehaviour kSms1{
    .table = TableId::Sms1,
    .roles = kSms1Roles,
    .modes = kSms1Modes,
    .limits_zero_mode = ControlMode::Position,
    .instructions = kSms1Instructions,
    .simulated_defaults = kSms1Identity,
    .return_delay_us_per_unit = 2.0,
    .return_delay_floor = 0,
    .degrees_per_position_unit = kDegreesPerStep,
    .degrees_per_s_per_speed_unit = 0.087,  // doc 000: run speed unit 0.087 °/s
    .phase_bit_speed_in_steps = 0,
    .degrees_per_s2_per_accel_unit = 100.0 * kDegreesPerStep,  // as sts (SMSCL SDK writes 41)
    .top_speed_degrees_per_s = kFeetechTopSpeed,
    .steps_per_turn = 4096,
    .centre_position = 2048,
    .power_on_position = 2048,
    .refused_bit = 0,  // Feetech firmware flags no refused write (docs/DECISIONS.md, Vendor fidelity)
    .checksum_bit = 0,
    .temperature_bit = feetech::error_bit::kTemperature,
    .overvoltage_bit = feetech::error_bit::kVoltage,
    .error_mask = 0x2F,
    .torque_on_status_bit = 0,
    .d55d_response_levels = false,
    .speed_zero_stops = false,
    .move_time_in_position_mode = true,
    .torque_128_calibrates = true,  // "older SMS: write 128 to torque enable" (docs/PROTOCOL.md §1.1)
    .factory_area_start = 0,
};

constexpr TableBehaviour kScs{
    .table = TableId::Scs,
    .roles = kScsRoles,
    .modes = {},
    .limits_zero_mode = ControlMode::Pwm,  // SCSCL SDK PWMMode: both limits 0, then duty to 44
    .instructions = kScsInstructions,
    .simulated_defaults = kScsIdentity,
    .return_delay_us_per_unit = 2.0,
    .return_delay_floor = 0,
    .degrees_per_position_unit = kScsDegreesPerStep,
    .degrees_per_s_per_speed_unit = kScsDegreesPerStep,  // steps/s (SCSCL SDK examples)
    .phase_bit_speed_in_steps = 0,
    .degrees_per_s2_per_accel_unit = 0.0,  // no acceleration field
    .top_speed_degrees_per_s = kScsTopSpeed,
    .steps_per_turn = 0,  // a 300° servo: no turn to wrap
    .centre_position = 512,
    .power_on_position = 512,
    .refused_bit = 0,
    .checksum_bit = 0,
    .temperature_bit = feetech::error_bit::kTemperature,
    .overvoltage_bit = feetech::error_bit::kVoltage,
    .error_mask = 0x2F,
    .torque_on_status_bit = 0,
    .d55d_response_levels = false,
    .speed_zero_stops = false,
    .move_time_in_position_mode = true,  // WritePos(id, position, time, speed)
    .torque_128_calibrates = false,
    .factory_area_start = 0,
};

constexpr TableBehaviour kD55d{
    .table = TableId::D55d,
    .roles = kD55dRoles,
    .modes = {},
    .limits_zero_mode = ControlMode::Velocity,
    .instructions = kD55dInstructions,
    .simulated_defaults = kD55dIdentity,
    .return_delay_us_per_unit = 500.0,
    .return_delay_floor = 0,
    .degrees_per_position_unit = 0.0,     // angle resolution × 0.1°
    .degrees_per_s_per_speed_unit = 0.0,  // position units per second
    .phase_bit_speed_in_steps = 0,
    .degrees_per_s2_per_accel_unit = 10.0,  // ×10 °/s²
    .top_speed_degrees_per_s = 360.0,
    .steps_per_turn = 0,
    .centre_position = 0,
    .power_on_position = 0,
    .refused_bit = d55d::error_bit::kInstruction,
    .checksum_bit = d55d::error_bit::kChecksum,
    .temperature_bit = d55d::error_bit::kOverTemperature,
    .overvoltage_bit = d55d::error_bit::kOverVoltage,
    .error_mask = 0x7F,
    .torque_on_status_bit = 0,
    .d55d_response_levels = true,
    .speed_zero_stops = true,
    .move_time_in_position_mode = false,
    .torque_128_calibrates = false,
    .factory_area_start = 0,
};

constexpr TableBehaviour kSmsmb{
    .table = TableId::Smsmb,
    .roles = kSmsmbRoles,
    .modes = kSmsmbModes,
    .limits_zero_mode = ControlMode::Position,
    .instructions = {},
    .simulated_defaults = kSmsmbIdentity,
    .return_delay_us_per_unit = 1.0,
    .return_delay_floor = 0,
    .degrees_per_position_unit = kDegreesPerStep,
    .degrees_per_s_per_speed_unit = kDegreesPerSPer0732Rpm,
    .phase_bit_speed_in_steps = 0,
    .degrees_per_s2_per_accel_unit = 8.79,
    .top_speed_degrees_per_s = kFeetechTopSpeed,
    .steps_per_turn = 4096,
    .centre_position = 2048,
    .power_on_position = 2048,
    .refused_bit = 0,  // Modbus answers with exceptions instead
    .checksum_bit = 0,
    .temperature_bit = 1 << 2,
    .overvoltage_bit = 1 << 0,
    .error_mask = 0x2F,  // bits 0-3 and 5 (the wiki names no bit 6 or 7); bit 4 is torque on
    .torque_on_status_bit = 1 << 4,
    .d55d_response_levels = false,
    .speed_zero_stops = false,
    .move_time_in_position_mode = false,
    .torque_128_calibrates = false,
    .factory_area_start = 0x180,
};

}  // namespace

const TableBehaviour& behaviour(TableId table) {
  switch (table) {
    case TableId::Sts: return kSts;
    case TableId::Sms1: return kSms1;
    case TableId::D55d: return kD55d;
    case TableId::Smsmb: return kSmsmb;
    case TableId::Scs: return kScs;
  }
  return kSts;
}

}  // namespace sms::simulator
