#include "simulator/virtual_servo.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <variant>

#include "modbus_map/baud_tables.h"
#include "modbus_map/tables.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"
#include "protocol/modbus_pdu.h"

namespace sms::simulator {

using modbus_map::Access;
using modbus_map::Area;
using modbus_map::FieldSpec;
using protocol::Bytes;
using protocol::Packet;
namespace common = protocol::common;
namespace feetech = protocol::feetech;
namespace d55d = protocol::d55d;

namespace {

// doc 002 §3.1, address 17: no command for 500 ms and the motor stops itself.
constexpr auto kHeartbeatTimeout = std::chrono::milliseconds(500);
// Photo switches of the simulated d55d motor: the CW one 30° clockwise of the power-on
// position, the CCW one 400° further; homing therefore records a travel of 400° (doc 002
// mentions travels beyond 360°). A switch reads high within ±2° of its position.
constexpr double kCwSwitchDegrees = -30.0;
constexpr double kSwitchTravelDegrees = 400.0;
constexpr double kSwitchWidthDegrees = 2.0;
// Plausible feedback for an SM40BL-class servo at 12 V: 12.1 V idle (docs/PROTOCOL.md §1.1 sample),
// 2.6 A at full load, 55 °C steady at full load from 25 °C ambient, thermal time constant 30 s.
constexpr double kIdleVoltageDeciVolt = 121.0;
constexpr double kCurrentUnitsPerLoadPermille = 0.4;  // 6.5 mA units
constexpr double kAmbientCelsius = 25.0;
constexpr double kCelsiusPerLoadPermille = 0.03;
constexpr double kThermalTimeConstant = 30.0;
// SMSMB fault reset (register 0x86) bit -> status bit it clears (docs/PROTOCOL.md §2.4).
struct FaultResetBit {
  std::uint16_t reset_bit;
  std::uint8_t status_bit;
};
constexpr FaultResetBit kFaultResetBits[] = {
    {1 << 0, 1 << 5},  // overload -> load
    {1 << 1, 1 << 3},  // over-current -> current
    {1 << 5, 1 << 0},  // voltage -> voltage
    {1 << 6, 1 << 2},  // overheat -> temperature
    {1 << 7, 1 << 1},  // encoder -> encoder
};
constexpr std::uint16_t kFaultResetSetCentre = 1 << 2;
constexpr std::int32_t kFactoryUnlock = 128;  // SMSMB lock value that opens the factory area
constexpr std::int32_t kTorqueCalibrate = 128;

// Modbus exception codes (Modbus application protocol §7).
constexpr std::uint8_t kIllegalFunction = 0x01;
constexpr std::uint8_t kIllegalAddress = 0x02;
constexpr std::uint8_t kIllegalValue = 0x03;
constexpr std::uint16_t kMaxReadRegisters = protocol::modbus_limits::kReadRegisters;
constexpr std::uint16_t kMaxWriteRegisters = protocol::modbus_limits::kWriteRegisters;

double seconds_between(Clock::time_point from, Clock::time_point to) {
  return std::chrono::duration<double>(to - from).count();
}

std::int32_t wrap(std::int64_t value, std::int32_t turn) {
  return static_cast<std::int32_t>(((value % turn) + turn) % turn);
}

std::uint16_t be16(std::span<const std::uint8_t> bytes, std::size_t offset) {
  return static_cast<std::uint16_t>(bytes[offset] << 8 | bytes[offset + 1]);
}

}  // namespace

// Instruction tables per protocol (docs/PROTOCOL.md §1.1, §1.2); a table's firmware may know fewer
// (TableBehaviour::instructions).
const std::array<VirtualServo::PacketInstruction, 12> VirtualServo::kFeetechInstructions{{
    {common::kPing, ReplyClass::Ping, &VirtualServo::on_ping},
    {common::kRead, ReplyClass::Read, &VirtualServo::on_read},
    {common::kWrite, ReplyClass::Other, &VirtualServo::on_write},
    {common::kRegWrite, ReplyClass::Other, &VirtualServo::on_reg_write},
    {common::kAction, ReplyClass::Other, &VirtualServo::on_action},
    {feetech::kRecovery, ReplyClass::Other, &VirtualServo::on_recovery},
    {feetech::kReboot, ReplyClass::Other, &VirtualServo::on_reboot},
    {feetech::kBackup, ReplyClass::Other, &VirtualServo::on_backup},
    {feetech::kResetStatus, ReplyClass::Other, &VirtualServo::on_reset_status},
    {feetech::kCalibrate, ReplyClass::Other, &VirtualServo::on_calibrate},
    {feetech::kSyncRead, ReplyClass::SyncRead, &VirtualServo::on_sync_read},
    {common::kSyncWrite, ReplyClass::Other, &VirtualServo::on_sync_write},
}};

const std::array<VirtualServo::PacketInstruction, 11> VirtualServo::kD55dInstructions{{
    {common::kPing, ReplyClass::Ping, &VirtualServo::on_ping},
    {common::kRead, ReplyClass::Read, &VirtualServo::on_read},
    {common::kWrite, ReplyClass::Other, &VirtualServo::on_write},
    {common::kRegWrite, ReplyClass::Other, &VirtualServo::on_reg_write},
    {common::kAction, ReplyClass::Other, &VirtualServo::on_action},
    {d55d::kReset, ReplyClass::Other, &VirtualServo::on_factory_reset},
    {d55d::kStartEnd, ReplyClass::Other, &VirtualServo::on_start_end},
    {d55d::kTrajectoryWrite, ReplyClass::Other, &VirtualServo::on_trajectory_write},
    {d55d::kTrajectoryAction, ReplyClass::Other, &VirtualServo::on_trajectory_action},
    {common::kSyncWrite, ReplyClass::Other, &VirtualServo::on_sync_write},
    {d55d::kCustom, ReplyClass::Other, &VirtualServo::on_custom},
}};

VirtualServo::VirtualServo(const ServoConfig& config, Clock::time_point now, std::chrono::milliseconds reboot_time,
                           double position_skew)
    : table_(&modbus_map::table(config.table)),
      behaviour_(&behaviour(config.table)),
      memory_(*table_),
      eeprom_(*table_),
      backup_(*table_),
      clock_(now),
      last_command_(now),
      deaf_until_(now),
      reboot_time_(reboot_time) {
  if (table_->protocol != config.protocol) {
    throw std::invalid_argument("servo " + std::to_string(config.id) + ": table " + std::string(table_->name) +
                                " is spoken over " + std::string(protocol::to_string(table_->protocol)) + ", not " +
                                std::string(protocol::to_string(config.protocol)));
  }
  for (const RoleBinding& binding : behaviour_->roles) {
    const FieldSpec* spec = modbus_map::field_by_name(*table_, binding.field);
    if (spec == nullptr) {
      throw std::logic_error("simulator: table " + std::string(table_->name) + " has no field named '" +
                             std::string(binding.field) + "' (simulator/table_behaviour.cpp is out of step)");
    }
    fields_[static_cast<std::size_t>(binding.role)] = spec;
  }
  memory_.reset_area(Area::Eeprom);
  memory_.reset_area(Area::Ram);
  for (const SimulatedDefault& identity : behaviour_->simulated_defaults) {
    const FieldSpec* spec = field(identity.role);
    if (spec != nullptr && !spec->default_value) memory_.store_value(*spec, identity.value);
  }
  const FieldSpec* id_field = field(Role::Id);
  if (id_field == nullptr || !ServoMemory::accepts(*id_field, config.id)) {
    throw std::invalid_argument("servo ID " + std::to_string(config.id) + " is outside table " +
                                std::string(table_->name) + "'s ID range " +
                                (id_field ? std::to_string(id_field->min) + ".." + std::to_string(id_field->max) : ""));
  }
  memory_.set_raw(*id_field, config.id);
  const auto code = modbus_map::baud_code(config.protocol, config.baud);
  if (!code) throw std::invalid_argument("servo " + std::to_string(config.id) + ": " + code.error());
  put(Role::BaudCode, *code);
  eeprom_ = memory_;
  backup_ = memory_;

  motion_ = MotionModel(behaviour_->power_on_position + position_skew);
  cw_switch_ = motion_.position() + units(kCwSwitchDegrees);
  ccw_switch_ = cw_switch_ + units(kSwitchTravelDegrees);
  power_on();
}

// --- identity and line ------------------------------------------------------------------

std::uint8_t VirtualServo::id() const { return static_cast<std::uint8_t>(get(Role::Id)); }

std::uint32_t VirtualServo::baud() const {
  const auto code = static_cast<std::uint8_t>(get(Role::BaudCode));
  if (const auto bps = modbus_map::baud_from_code(protocol(), code)) return *bps;
  // sms1: "other values fall back to 1 M" — generalised to the protocol's code 0.
  return modbus_map::baud_from_code(protocol(), 0).value_or(0);
}

Clock::duration VirtualServo::return_delay() const {
  const std::int32_t units = std::max(get(Role::ReturnDelay), behaviour_->return_delay_floor);
  const double micros = units * behaviour_->return_delay_us_per_unit;
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double, std::micro>(micros));
}

bool VirtualServo::listening(Clock::time_point now) const { return !offline_ && now >= deaf_until_; }

// --- table access ---------------------------------------------------------------------------

std::optional<Role> VirtualServo::role_of(const FieldSpec& spec) const {
  for (std::size_t index = 0; index < fields_.size(); ++index) {
    if (fields_[index] == &spec) return static_cast<Role>(index);
  }
  return std::nullopt;
}

std::int32_t VirtualServo::get(Role role, std::int32_t fallback) const {
  const FieldSpec* spec = field(role);
  return spec != nullptr ? memory_.value(*spec) : fallback;
}

void VirtualServo::put(Role role, std::int64_t value) {
  if (const FieldSpec* spec = field(role)) memory_.store_value(*spec, value);
}

bool VirtualServo::eeprom_unlocked() const {
  if (field(Role::Lock) == nullptr) return true;  // d55d: EEPROM writes always persist
  const std::int32_t lock = get(Role::Lock);
  return lock == 0 || (behaviour_->factory_area_start != 0 && lock == kFactoryUnlock);
}

void VirtualServo::persist(const FieldSpec& spec) {
  if (eeprom_.raw(spec) == memory_.raw(spec)) return;
  eeprom_.set_raw(spec, memory_.raw(spec));
  persist_dirty_ = true;
}

VirtualServo::WriteResult VirtualServo::write_checked(std::uint16_t address, std::span<const std::uint8_t> bytes,
                                                      WriteCheck check) {
  const std::size_t unit = memory_.unit_size();
  if (bytes.empty() || bytes.size() % unit != 0) return WriteResult::NotWritable;
  const auto count = static_cast<std::uint32_t>(bytes.size() / unit);
  if (!memory_.contains(address, count)) return WriteResult::NotWritable;

  ServoMemory trial = memory_;
  std::copy(bytes.begin(), bytes.end(), trial.wire(address, static_cast<std::uint16_t>(count)).begin());
  std::vector<const FieldSpec*> touched;
  for (std::uint32_t offset = 0; offset < count; ++offset) {
    const auto addr = static_cast<std::uint16_t>(address + offset);
    const FieldSpec* spec = modbus_map::field_covering(*table_, addr);
    if (spec == nullptr) {
      if (check == WriteCheck::Modbus) return WriteResult::NotWritable;
      // A byte of no field: the firmware has nothing there, the write does not land.
      const auto kept = memory_.wire(addr, 1);
      std::copy(kept.begin(), kept.end(), trial.wire(addr, 1).begin());
      continue;
    }
    if (touched.empty() || touched.back() != spec) touched.push_back(spec);
  }
  const bool factory_locked = get(Role::Lock) != kFactoryUnlock;
  const auto writable = [&](const FieldSpec& spec) {
    return spec.access != Access::ReadOnly &&
           !(behaviour_->factory_area_start != 0 && spec.addr >= behaviour_->factory_area_start && factory_locked);
  };
  // SMSMB answers a refused write with an exception, d55d with its instruction bit: either way
  // nothing is written. Feetech firmware flags nothing (status bit 4 is unused): a field that
  // is read-only or would get a value outside its range keeps its value, the rest lands.
  const bool refuse_whole = check == WriteCheck::Modbus || behaviour_->refused_bit != 0;
  if (check == WriteCheck::Backdoor) {
    // tests: anything inside the table lands
  } else if (refuse_whole) {
    for (const FieldSpec* spec : touched) {
      if (!writable(*spec)) return WriteResult::NotWritable;
    }
    for (const FieldSpec* spec : touched) {
      if (!ServoMemory::accepts(*spec, trial.raw(*spec))) return WriteResult::BadValue;
    }
  } else {
    std::erase_if(touched, [&](const FieldSpec* spec) {
      if (writable(*spec) && ServoMemory::accepts(*spec, trial.raw(*spec))) return false;
      trial.set_raw(*spec, memory_.raw(*spec));
      return true;
    });
  }
  if (check == WriteCheck::DryRun) return WriteResult::Ok;
  const ServoMemory before = memory_;
  memory_ = std::move(trial);
  apply_written(before, touched);
  return WriteResult::Ok;
}

bool VirtualServo::write_raw(std::uint16_t address, std::span<const std::uint8_t> bytes, Clock::time_point now) {
  update(now);
  const bool written = write_checked(address, bytes, WriteCheck::Backdoor) == WriteResult::Ok;
  refresh_present();
  return written;
}

// --- behaviour ------------------------------------------------------------------------------

double VirtualServo::degrees_per_unit() const {
  if (behaviour_->degrees_per_position_unit > 0) return behaviour_->degrees_per_position_unit;
  const std::int32_t resolution = get(Role::AngleResolution, 10);  // ×0.1° (doc 002, address 13)
  return std::max(resolution, 1) * 0.1;
}

double VirtualServo::degrees_per_s_per_speed_unit() const {
  const std::uint8_t phase_bit = behaviour_->phase_bit_speed_in_steps;
  if (phase_bit != 0 && (get(Role::Phase) & phase_bit) != 0) return degrees_per_unit();  // 1 step/s
  return behaviour_->degrees_per_s_per_speed_unit;
}

double VirtualServo::speed_units(std::int32_t speed_field_value) const {
  const double magnitude = std::abs(static_cast<double>(speed_field_value));
  const double unit = degrees_per_s_per_speed_unit();
  const double per_second = unit > 0 ? units(magnitude * unit) : magnitude;
  return std::copysign(std::min(per_second, units(behaviour_->top_speed_degrees_per_s)),
                       static_cast<double>(speed_field_value));
}

MotionLimits VirtualServo::motion_limits(std::int32_t speed_field_value) const {
  MotionLimits limits;
  const double top = units(behaviour_->top_speed_degrees_per_s);
  // Goal speed 0 asks for the maximum (docs/PROTOCOL.md §2.1, doc 000 §0x2A).
  limits.max_speed = speed_field_value == 0 ? top : std::abs(speed_units(speed_field_value));
  if (field(Role::Acceleration) != nullptr) {
    limits.acceleration = units(get(Role::Acceleration) * behaviour_->degrees_per_s2_per_accel_unit);
  }
  limits.deceleration = field(Role::Deceleration) != nullptr
                            ? units(get(Role::Deceleration) * behaviour_->degrees_per_s2_per_accel_unit)
                            : limits.acceleration;
  return limits;
}

ControlMode VirtualServo::control_mode() const {
  if (behaviour_->modes.empty()) {
    // No mode byte: both angle limits 0 select the other mode (d55d wheel, doc 002 §3.2; scs
    // open-loop motor, SCSCL SDK PWMMode).
    return get(Role::MinLimit) == 0 && get(Role::MaxLimit) == 0 ? behaviour_->limits_zero_mode : ControlMode::Position;
  }
  const std::int32_t mode = get(Role::Mode);
  for (const ModeBinding& binding : behaviour_->modes) {
    if (binding.value == mode) return binding.mode;
  }
  return ControlMode::Position;
}

bool VirtualServo::multi_turn() const {
  const ControlMode mode = control_mode();
  return behaviour_->steps_per_turn > 0 &&
         (mode == ControlMode::Step || ((mode == ControlMode::Position || mode == ControlMode::PositionRelease) &&
                                        get(Role::MinLimit) == 0 && get(Role::MaxLimit) == 0));
}

bool VirtualServo::torque_on() const {
  if (field(Role::TorqueEnable) != nullptr) return get(Role::TorqueEnable) == 1;
  return get(Role::Sleep) == 0;
}

std::uint8_t VirtualServo::error_bits() const { return injected_errors_ & behaviour_->error_mask; }

void VirtualServo::normalise_single_turn() {
  const std::int32_t turn = behaviour_->steps_per_turn;
  if (turn <= 0) return;
  const double turns = std::floor(motion_.position() / turn);
  if (turns != 0) motion_.shift(-turns * turn);
}

void VirtualServo::power_on() {
  memory_.reset_area(Area::Ram);
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area == Area::Eeprom) memory_.set_raw(spec, eeprom_.raw(spec));
  }
  // sts: max torque is copied to the torque limit at power-on (docs/PROTOCOL.md §2.1, address 16).
  if (field(Role::MaxTorque) != nullptr) put(Role::TorqueLimit, get(Role::MaxTorque));
  reg_write_.reset();
  trajectory_next_.reset();
  homing_phase_ = HomingPhase::Idle;
  homing_status_ = 0;
  pending_error_ = 0;
  // The multi-turn count is not kept over a power cycle (doc 001 §9).
  normalise_single_turn();
  // d55d: "must not move at power-on until commanded" — every servo powers up holding still.
  if (torque_on()) {
    motion_.hold();
  } else {
    motion_.release();
  }
  put(Role::GoalPosition, std::lround(motion_.position()));
  refresh_present();
}

void VirtualServo::reboot() {
  deaf_until_ = clock_ + reboot_time_;
  power_on();
}

void VirtualServo::stop_commands() {
  trajectory_next_.reset();
  if (homing_phase_ != HomingPhase::Idle) stop_homing(3);
}

void VirtualServo::apply_written(const ServoMemory& before, std::span<const FieldSpec* const> written) {
  bool goal_written = false;
  bool speed_written = false;
  bool duty_written = false;
  bool motion_changed = false;
  bool torque_switched_on = false;
  for (const FieldSpec* spec : written) {
    if (spec->area == Area::Eeprom && eeprom_unlocked()) persist(*spec);
    const auto role = role_of(*spec);
    if (!role) continue;
    switch (*role) {
      case Role::GoalPosition: goal_written = true; break;
      case Role::GoalSpeed:
        speed_written = true;
        motion_changed = true;
        break;
      case Role::GoalTime:
        duty_written = true;
        motion_changed = true;
        break;
      case Role::Mode:
      case Role::MinLimit:
      case Role::MaxLimit:
      case Role::Acceleration:
      case Role::Deceleration:
      case Role::TorqueLimit:
      case Role::Sleep: motion_changed = true; break;
      case Role::TorqueEnable: {
        const std::int32_t value = get(Role::TorqueEnable);
        if (value == kTorqueCalibrate && behaviour_->torque_128_calibrates) {
          // Mid-point calibration; the torque switch then reads 0 (doc 001 §15, address 40).
          calibrate(behaviour_->centre_position);
          put(Role::TorqueEnable, 0);
          motion_.release();
        } else if (value == 1 && before.value(*spec) != 1) {
          torque_switched_on = true;  // holds where it is, not at a stale goal
        }
        motion_changed = true;
        break;
      }
      case Role::PositionOffset: {
        // present = encoder - offset: a new offset moves the reading, not the motor.
        const std::int32_t delta = memory_.value(*spec) - before.value(*spec);
        motion_.shift(-delta);
        break;
      }
      case Role::AngleResolution: {
        // d55d positions are counted in resolution units: rescale, the motor stays.
        const std::int32_t old_resolution = std::max(before.value(*spec), 1);
        const std::int32_t new_resolution = std::max(memory_.value(*spec), 1);
        const double scale = static_cast<double>(old_resolution) / new_resolution;
        motion_ = MotionModel(motion_.position() * scale);
        cw_switch_ *= scale;
        ccw_switch_ *= scale;
        motion_changed = true;
        break;
      }
      case Role::Brake:
        if (get(Role::Brake) != 0) {
          stop_commands();
          motion_.hold();
        }
        motion_changed = true;
        break;
      case Role::Homing:
        if ((memory_.raw(*spec) & 0x0F) == 1) {
          start_homing();
        } else {
          stop_homing(0);
        }
        break;
      case Role::ClearUnload: memory_.set_raw(*spec, 0); break;
      case Role::FaultReset: {
        const std::uint32_t bits = memory_.raw(*spec);
        for (const FaultResetBit& mapping : kFaultResetBits) {
          if ((bits & mapping.reset_bit) != 0) injected_errors_ &= static_cast<std::uint8_t>(~mapping.status_bit);
        }
        if ((bits & kFaultResetSetCentre) != 0) calibrate(behaviour_->centre_position);
        memory_.set_raw(*spec, 0);
        break;
      }
      default: break;
    }
  }
  // The command of the present mode: a goal position, a speed in constant-speed mode, a duty
  // in PWM mode.
  const ControlMode mode = control_mode();
  const bool commanded =
      goal_written || (speed_written && mode == ControlMode::Velocity) || (duty_written && mode == ControlMode::Pwm);
  if (commanded && field(Role::TorqueEnable) != nullptr && get(Role::TorqueEnable) != 1) {
    // A command switches the torque on, as after a protection trip (doc 001 §15, address 28:
    // "write a position command again to lift the protection"), from damping (2) too; Feetech's
    // own examples (FTServo_Linux WriteSpe, SCSCL WritePWM) command speed and PWM without
    // enabling the torque first.
    put(Role::TorqueEnable, 1);
  } else if (torque_switched_on && !goal_written) {
    normalise_single_turn();
    put(Role::GoalPosition, std::lround(motion_.position()));
  }
  if (goal_written || motion_changed) {
    stop_commands();  // a new command ends a trajectory or a homing run
    drive_from_table(goal_written);
  }
}

void VirtualServo::drive_from_table(bool goal_written) {
  if (get(Role::Brake) != 0) {
    motion_.hold();
    return;
  }
  if (!torque_on()) {
    motion_.release();
    return;
  }
  const std::int32_t speed = get(Role::GoalSpeed);
  if (behaviour_->speed_zero_stops && speed == 0) {
    motion_.release();  // d55d: speed 0 stops at once, without torque (doc 002, rule 3)
    return;
  }
  MotionLimits limits = motion_limits(speed);
  const ControlMode mode = control_mode();
  switch (mode) {
    case ControlMode::Position:
    case ControlMode::PositionRelease: {
      double target = get(Role::GoalPosition);
      if (!multi_turn()) {
        normalise_single_turn();
        const double clamped = std::clamp<double>(target, get(Role::MinLimit), get(Role::MaxLimit));
        if (clamped != target) put(Role::GoalPosition, std::lround(clamped));  // "equals the limit" (doc 000)
        target = clamped;
      }
      const std::int32_t move_ms = get(Role::GoalTime);
      if (behaviour_->move_time_in_position_mode && speed == 0 && move_ms > 0) {
        // sms1: run time in ms when no run speed is given (doc 000 §0x2A).
        const double distance = std::abs(target - motion_.position());
        if (distance > 0) limits.max_speed = std::min(limits.max_speed, distance * 1000.0 / move_ms);
      }
      motion_.move_to(target, limits);
      if (goal_written) {
        move_started_ = clock_;
        arrived_at_.reset();
        position_at_goal_ = motion_.position();
        read_before_goal_ = position_at_read_;
        // A goal where the motor stands is reached the moment it is written.
        if (motion_.arrived()) arrived_at_ = clock_;
      }
      break;
    }
    case ControlMode::Velocity:
      if (behaviour_->modes.empty() && goal_written) {
        // d55d wheel mode: the goal is a relative angle in the run speed's direction (doc 002 §0x1E).
        const double direction = speed < 0 ? -1.0 : 1.0;
        motion_.move_to(motion_.position() + direction * get(Role::GoalPosition), limits);
      } else {
        motion_.run_at(speed == 0 ? 0.0 : speed_units(speed), limits);
      }
      break;
    case ControlMode::Pwm: {
      // Open loop: the duty cycle (0.1 %, direction bit 10) sets the no-load speed.
      const double duty = get(Role::GoalTime) / 1000.0;
      motion_.run_at(duty * units(behaviour_->top_speed_degrees_per_s), limits);
      break;
    }
    case ControlMode::Step:
      if (goal_written) {
        const double base = motion_.drive() == MotionModel::Drive::Position ? motion_.target() : motion_.position();
        motion_.move_to(base + get(Role::GoalPosition), limits);
      } else if (motion_.drive() == MotionModel::Drive::Position) {
        motion_.move_to(motion_.target(), limits);
      } else {
        motion_.hold();
      }
      break;
  }
}

void VirtualServo::calibrate(std::int32_t present) {
  const std::int32_t turn = behaviour_->steps_per_turn;
  const FieldSpec* offset_field = field(Role::PositionOffset);
  if (turn <= 0 || offset_field == nullptr) return;
  const std::int32_t shown = wrap(std::lround(motion_.position()), turn);
  const std::int32_t old_offset = get(Role::PositionOffset);
  // The offset that makes the reading `present`, folded into the field's ±half-turn range.
  std::int32_t wanted = wrap(old_offset + shown - present + turn / 2, turn) - turn / 2;
  wanted = std::clamp(wanted, offset_field->min, offset_field->max);
  memory_.store_value(*offset_field, wanted);
  motion_.shift(-(wanted - old_offset));
  normalise_single_turn();
  // The calibration is stored whatever the lock says (the FD tool's one-key centring survives
  // a power cycle).
  persist(*offset_field);
  put(Role::GoalPosition, std::lround(motion_.position()));
}

void VirtualServo::start_homing() {
  trajectory_next_.reset();
  // Address 19: 1 = zero on the clockwise side, 2 = counter-clockwise.
  const bool zero_ccw = get(Role::HomingDirection) == 2;
  zero_switch_ = zero_ccw ? ccw_switch_ : cw_switch_;
  end_switch_ = zero_ccw ? cw_switch_ : ccw_switch_;
  homing_phase_ = HomingPhase::SeekZero;
  homing_status_ = 1;
  const double top = units(behaviour_->top_speed_degrees_per_s);
  motion_.move_to(zero_switch_, MotionLimits{top, 0, 0});
}

void VirtualServo::stop_homing(std::uint8_t status) {
  if (homing_phase_ != HomingPhase::Idle) motion_.hold();
  homing_phase_ = HomingPhase::Idle;
  homing_status_ = status;
}

void VirtualServo::next_trajectory_point() {
  if (!trajectory_next_ || *trajectory_next_ >= trajectory_.size()) {
    trajectory_next_.reset();
    return;
  }
  const d55d::TrajectoryPoint point = trajectory_[(*trajectory_next_)++];
  if (point.speed == 0) {
    trajectory_next_.reset();
    motion_.release();  // speed 0 stops, whatever the motor is doing (doc 002, rule 3)
    return;
  }
  MotionLimits limits = motion_limits(point.speed);
  put(Role::GoalPosition, point.angle);
  motion_.move_to(point.angle, limits);
}

void VirtualServo::on_arrival() {
  if (homing_phase_ == HomingPhase::SeekZero) {
    // Zero found: it becomes position 0, then the motor turns back toward the end switch.
    const double delta = -zero_switch_;
    motion_.shift(delta);
    cw_switch_ += delta;
    ccw_switch_ += delta;
    end_switch_ += delta;
    zero_switch_ = 0;
    accumulated_ = 0;
    homing_phase_ = HomingPhase::SeekEnd;
    motion_.move_to(end_switch_, motion_.limits());
    return;
  }
  if (homing_phase_ == HomingPhase::SeekEnd) {
    // The travel from zero to end is the motor's maximum angle (doc 002 rule 2, address 20).
    put(Role::MaxLimit, std::lround(std::abs(end_switch_)));
    if (const FieldSpec* spec = field(Role::MaxLimit)) persist(*spec);
    homing_phase_ = HomingPhase::Idle;
    homing_status_ = 2;
    motion_.hold();
    put(Role::GoalPosition, std::lround(motion_.position()));
    return;
  }
  if (trajectory_next_) {
    next_trajectory_point();
    return;
  }
  if (control_mode() == ControlMode::PositionRelease) {
    motion_.release();
    put(Role::TorqueEnable, 0);
  }
}

void VirtualServo::advance_motion(double seconds) {
  const Clock::time_point start = clock_;
  double elapsed = 0;
  while (seconds > 0) {
    const bool hooked = trajectory_next_.has_value() || homing_phase_ != HomingPhase::Idle ||
                        (control_mode() == ControlMode::PositionRelease && torque_on());
    const double chunk = hooked && !motion_.steady() ? std::min(seconds, 0.001) : seconds;
    const double before = motion_.position();
    const std::optional<double> arrival = motion_.advance(chunk);
    if (arrival && move_started_ && !arrived_at_) {
      arrived_at_ =
          start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(elapsed + *arrival));
    }
    accumulated_ += motion_.position() - before;
    seconds -= chunk;
    elapsed += chunk;
    if (hooked && motion_.arrived()) on_arrival();
  }
}

double VirtualServo::load_permille() const {
  if (motion_.drive() == MotionModel::Drive::Free) return 0;
  // Holding costs a little, speed costs friction, acceleration costs inertia; the torque
  // limit caps it (docs/PROTOCOL.md §2.1 address 48).
  const double top = units(behaviour_->top_speed_degrees_per_s);
  const double speed = std::abs(motion_.velocity());
  const double friction = speed > 0 ? 40.0 + 160.0 * speed / top : 0.0;
  const double inertia = std::abs(motion_.acceleration()) / top * 60.0;
  const double magnitude = std::min<double>(get(Role::TorqueLimit, 1000), 8.0 + friction + inertia);
  const double sign =
      motion_.velocity() != 0 ? motion_.velocity() : (motion_.acceleration() != 0 ? motion_.acceleration() : 1.0);
  return std::copysign(magnitude, sign);
}

bool VirtualServo::heartbeat_armed() const {
  if (get(Role::Heartbeat) == 0) return false;
  switch (motion_.drive()) {
    case MotionModel::Drive::Position: return !motion_.arrived();
    case MotionModel::Drive::Velocity: return motion_.commanded_velocity() != 0 || motion_.velocity() != 0;
    default: return false;
  }
}

void VirtualServo::update(Clock::time_point now) {
  if (now <= clock_) return;
  const double elapsed = seconds_between(clock_, now);
  while (clock_ < now) {
    Clock::time_point until = now;
    const bool heartbeat = heartbeat_armed();
    const Clock::time_point deadline = last_command_ + kHeartbeatTimeout;
    if (heartbeat && deadline < until) until = std::max(deadline, clock_);
    advance_motion(seconds_between(clock_, until));
    clock_ = until;
    if (heartbeat && clock_ >= deadline) {
      // Heartbeat (d55d address 17): silence for 500 ms stops the motor.
      ++heartbeat_stops_;
      stop_commands();
      motion_.hold();
      put(Role::GoalPosition, std::lround(motion_.position()));
    }
  }
  const double target = kAmbientCelsius + kCelsiusPerLoadPermille * std::abs(load_permille());
  temperature_ += (target - temperature_) * (1.0 - std::exp(-elapsed / kThermalTimeConstant));
  refresh_present();
}

void VirtualServo::refresh_present() {
  const std::int32_t turn = behaviour_->steps_per_turn;
  const bool wraps = turn > 0 && !multi_turn();
  const auto shown = [&](double position) {
    const auto rounded = std::lround(position);
    return wraps ? wrap(rounded, turn) : static_cast<std::int32_t>(rounded);
  };
  put(Role::PresentPosition, shown(motion_.position()));
  put(Role::PresentGoal, shown(motion_.target()));

  const double velocity = motion_.velocity();
  const double speed_unit = degrees_per_s_per_speed_unit();
  const double speed_field = speed_unit > 0 ? velocity * degrees_per_unit() / speed_unit : velocity;
  put(Role::PresentSpeed, std::lround(speed_field));

  const double load = load_permille();
  put(Role::PresentLoad, std::lround(load));
  put(Role::PresentCurrent, std::lround(load * kCurrentUnitsPerLoadPermille));

  const std::uint8_t errors = error_bits();
  double voltage = kIdleVoltageDeciVolt - std::abs(load) * kCurrentUnitsPerLoadPermille / 50.0;
  // A table without a configured limit (0) gets a typical one: 14.0 V, 70 °C.
  const auto limit_or = [](std::int32_t limit, std::int32_t typical) { return limit > 0 ? limit : typical; };
  if ((errors & behaviour_->overvoltage_bit) != 0) voltage = limit_or(get(Role::MaxVoltage), 140) + 5;
  put(Role::PresentVoltage, std::lround(voltage));
  double temperature = temperature_;
  if ((errors & behaviour_->temperature_bit) != 0) {
    temperature = std::max(temperature, limit_or(get(Role::MaxTemperature), 70) + 3.0);
  }
  put(Role::PresentTemperature, std::lround(temperature));

  put(Role::Status, errors | (torque_on() ? behaviour_->torque_on_status_bit : 0));
  const bool moving = velocity != 0 || (motion_.drive() == MotionModel::Drive::Position && !motion_.arrived());
  put(Role::Moving, moving ? 1 : 0);
  put(Role::RegWriteFlag, reg_write_ ? 1 : 0);
  // d55d accumulated angle: a 16-bit counter that wraps (doc 002 §0x28).
  put(Role::AccumulatedAngle,
      static_cast<std::int16_t>(static_cast<std::uint16_t>(std::llround(accumulated_) & 0xFFFF)));
  if (const FieldSpec* spec = field(Role::Homing))
    memory_.set_raw(*spec, static_cast<std::uint32_t>(homing_status_) << 4);
  if (field(Role::PhotoSwitchState) != nullptr) {
    const double width = units(kSwitchWidthDegrees);
    const double position = motion_.position();
    const std::int32_t state =
        (std::abs(position - cw_switch_) <= width ? 1 : 0) | (std::abs(position - ccw_switch_) <= width ? 2 : 0);
    put(Role::PhotoSwitchState, state);
  }
}

void VirtualServo::set_error_bits(std::uint8_t bits, Clock::time_point now) {
  update(now);
  injected_errors_ = bits;
  // Unload conditions (sts 19, sms1 19, d55d 18): a matching error takes the torque off.
  if ((error_bits() & get(Role::UnloadConditions)) != 0 && torque_on()) {
    stop_commands();
    motion_.release();
    put(Role::TorqueEnable, 0);
  }
  refresh_present();
}

// --- packet protocols -----------------------------------------------------------------------

bool VirtualServo::answers(ReplyClass reply, bool broadcast) const {
  const std::int32_t level = get(Role::ResponseLevel, behaviour_->d55d_response_levels ? 2 : 1);
  switch (reply) {
    case ReplyClass::Ping:
    case ReplyClass::SyncRead: return true;
    case ReplyClass::Read: return !broadcast && (!behaviour_->d55d_response_levels || level >= 1);
    case ReplyClass::Other: return !broadcast && level >= (behaviour_->d55d_response_levels ? 2 : 1);
  }
  return false;
}

std::optional<Packet> VirtualServo::handle_packet(const Packet& request, Clock::time_point now) {
  update(now);
  const std::uint8_t reply_id = id();
  const bool broadcast = request.id == protocol::kBroadcastId;
  if (!broadcast && request.id != reply_id) return std::nullopt;
  last_command_ = now;

  const std::span<const PacketInstruction> instructions =
      protocol() == protocol::BusProtocol::D55d ? std::span<const PacketInstruction>(kD55dInstructions)
                                                : std::span<const PacketInstruction>(kFeetechInstructions);
  const auto& known = behaviour_->instructions;
  const auto instruction = std::find_if(instructions.begin(), instructions.end(), [&](const PacketInstruction& entry) {
    return entry.code == request.code && std::find(known.begin(), known.end(), entry.code) != known.end();
  });
  Outcome outcome;
  ReplyClass reply = ReplyClass::Other;
  if (instruction != instructions.end()) {
    reply = instruction->reply;
    outcome = (this->*(instruction->handler))(request);
  } else {
    outcome.error = behaviour_->refused_bit;  // unknown to this firmware
  }
  refresh_present();
  if (!outcome.answer || !answers(reply, broadcast)) return std::nullopt;
  const auto error = static_cast<std::uint8_t>(outcome.error | error_bits() | pending_error_);
  pending_error_ = 0;
  return protocol::status(reply_id, error, outcome.data);
}

void VirtualServo::note_checksum_error() { pending_error_ |= behaviour_->checksum_bit; }

VirtualServo::Outcome VirtualServo::on_ping(const Packet&) {
  Outcome outcome;
  // d55d's PING reply carries one parameter (doc 002 §2.4.5: `D5 5D ID 03 ERR 00 CHK`).
  if (protocol() == protocol::BusProtocol::D55d) outcome.data = {0x00};
  return outcome;
}

VirtualServo::Outcome VirtualServo::on_read(const Packet& request) {
  const auto read = protocol::parse_read(request.params);
  if (!read || !memory_.contains(read->address, read->count)) return {true, behaviour_->refused_bit, {}};
  const auto bytes = memory_.wire(read->address, read->count);
  position_at_read_ = motion_.position();
  return {true, 0, Bytes(bytes.begin(), bytes.end())};
}

VirtualServo::Outcome VirtualServo::on_write(const Packet& request) {
  const auto write = protocol::parse_write(request.params);
  if (!write || write_checked(write->address, write->data, WriteCheck::Bus) != WriteResult::Ok) {
    return {true, behaviour_->refused_bit, {}};  // nothing written (docs/PROTOCOL.md §1)
  }
  return {};
}

VirtualServo::Outcome VirtualServo::on_reg_write(const Packet& request) {
  const auto write = protocol::parse_write(request.params);
  if (!write || write_checked(write->address, write->data, WriteCheck::DryRun) != WriteResult::Ok) {
    return {true, behaviour_->refused_bit, {}};
  }
  reg_write_ = PendingWrite{write->address, write->data};
  return {};
}

VirtualServo::Outcome VirtualServo::on_action(const Packet&) {
  if (!reg_write_) {
    // d55d flags ACTION without REG WRITE (doc 002 §2.3 bit 5); feetech ignores it.
    return {true, static_cast<std::uint8_t>(behaviour_->d55d_response_levels ? behaviour_->refused_bit : 0), {}};
  }
  const PendingWrite pending = std::move(*reg_write_);
  reg_write_.reset();
  write_checked(pending.address, pending.data, WriteCheck::Bus);
  return {};
}

VirtualServo::Outcome VirtualServo::on_sync_write(const Packet& request) {
  if (const auto sync = protocol::parse_sync_write(request.params)) {
    const std::uint8_t own = id();
    for (const auto& entry : sync->entries) {
      if (entry.id == own) {
        write_checked(sync->address, entry.data, WriteCheck::Bus);
        break;
      }
    }
  }
  return {false, 0, {}};
}

VirtualServo::Outcome VirtualServo::on_sync_read(const Packet& request) {
  const auto sync = feetech::parse_sync_read(request.params);
  if (!sync || std::find(sync->ids.begin(), sync->ids.end(), id()) == sync->ids.end()) return {false, 0, {}};
  if (!memory_.contains(sync->address, sync->count)) return {true, behaviour_->refused_bit, {}};
  const auto bytes = memory_.wire(sync->address, sync->count);
  position_at_read_ = motion_.position();
  return {true, 0, Bytes(bytes.begin(), bytes.end())};
}

VirtualServo::Outcome VirtualServo::on_recovery(const Packet&) {
  // Every EEPROM parameter but the ID back from the backup; kept over a power cycle only when
  // the EEPROM is unlocked (docs/PROTOCOL.md §1.1).
  const ServoMemory before = memory_;
  std::vector<const FieldSpec*> restored;
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area != Area::Eeprom || &spec == field(Role::Id) || spec.access == Access::ReadOnly) continue;
    if (memory_.raw(spec) == backup_.raw(spec)) continue;
    memory_.set_raw(spec, backup_.raw(spec));
    restored.push_back(&spec);
  }
  apply_written(before, restored);
  return {};
}

VirtualServo::Outcome VirtualServo::on_reboot(const Packet&) {
  reboot();
  return {false, 0, {}};  // no answer (docs/PROTOCOL.md §1.1)
}

VirtualServo::Outcome VirtualServo::on_backup(const Packet&) {
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area == Area::Eeprom) backup_.set_raw(spec, memory_.raw(spec));
  }
  persist_dirty_ = true;
  return {};
}

VirtualServo::Outcome VirtualServo::on_reset_status(const Packet&) {
  normalise_single_turn();  // the multi-turn count is cleared
  put(Role::GoalPosition, std::lround(motion_.target()));
  return {};
}

VirtualServo::Outcome VirtualServo::on_calibrate(const Packet& request) {
  const auto position = feetech::parse_calibrate(request.params);
  const std::int32_t turn = behaviour_->steps_per_turn;
  if (!position || (position->has_value() && **position >= turn)) return {true, behaviour_->refused_bit, {}};
  calibrate(position->value_or(behaviour_->centre_position));
  return {};
}

VirtualServo::Outcome VirtualServo::on_factory_reset(const Packet&) {
  memory_.reset_area(Area::Eeprom);
  for (const SimulatedDefault& identity : behaviour_->simulated_defaults) {
    const FieldSpec* spec = field(identity.role);
    if (spec != nullptr && !spec->default_value) memory_.store_value(*spec, identity.value);
  }
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area == Area::Eeprom) persist(spec);
  }
  persist_dirty_ = true;
  power_on();
  return {};
}

VirtualServo::Outcome VirtualServo::on_start_end(const Packet& request) {
  // The document gives no layout; taken as start L/H, end L/H = the CW and CCW limits.
  const FieldSpec* start = field(Role::MinLimit);
  const FieldSpec* end = field(Role::MaxLimit);
  if (request.params.size() != 4 || start == nullptr || end == nullptr) return {true, behaviour_->refused_bit, {}};
  ServoMemory trial = memory_;
  trial.set_raw(*start, modbus_map::load_raw(std::span(request.params).first(2), 2, memory_.byte_order()));
  trial.set_raw(*end, modbus_map::load_raw(std::span(request.params).subspan(2, 2), 2, memory_.byte_order()));
  if (!ServoMemory::accepts(*start, trial.raw(*start)) || !ServoMemory::accepts(*end, trial.raw(*end))) {
    return {true, behaviour_->refused_bit, {}};
  }
  const ServoMemory before = memory_;
  memory_ = trial;
  const std::array<const FieldSpec*, 2> written{start, end};
  apply_written(before, written);
  return {};
}

VirtualServo::Outcome VirtualServo::on_trajectory_write(const Packet& request) {
  auto points = d55d::parse_trajectory_write(request.params);
  if (!points) return {true, behaviour_->refused_bit, {}};
  trajectory_ = std::move(*points);
  return {};
}

VirtualServo::Outcome VirtualServo::on_trajectory_action(const Packet&) {
  if (trajectory_.empty() || !torque_on() || get(Role::Brake) != 0) return {true, behaviour_->refused_bit, {}};
  if (homing_phase_ != HomingPhase::Idle) stop_homing(3);
  trajectory_next_ = 0;
  next_trajectory_point();
  return {};
}

VirtualServo::Outcome VirtualServo::on_custom(const Packet& request) {
  const auto move = d55d::parse_custom(request.params);
  if (!move || get(Role::Brake) != 0 || !torque_on()) return {true, behaviour_->refused_bit, {}};
  const FieldSpec* speed_field = field(Role::GoalSpeed);
  const auto set_accel = [&](std::optional<std::uint8_t> acceleration, std::optional<std::uint8_t> deceleration) {
    if (acceleration) put(Role::Acceleration, *acceleration);
    if (deceleration) put(Role::Deceleration, *deceleration);
  };
  stop_commands();
  std::visit(
      [&](const auto& command) {
        using Command = std::decay_t<decltype(command)>;
        if constexpr (std::is_same_v<Command, d55d::ChangeSpeed>) {
          // Base motors: new magnitude, direction kept (doc 002 custom 3).
          const std::uint32_t direction = speed_field ? memory_.raw(*speed_field) & 0x8000U : 0;
          if (speed_field) memory_.set_raw(*speed_field, direction | (command.speed & 0x7FFFU));
          drive_from_table(false);
        } else {
          if (speed_field) memory_.set_raw(*speed_field, command.speed);
          set_accel(command.acceleration, command.deceleration);
          const std::int32_t speed = get(Role::GoalSpeed);
          if (speed == 0) {
            motion_.release();  // speed 0 stops (doc 002, rule 3)
            return;
          }
          double target = 0;
          if constexpr (std::is_same_v<Command, d55d::RelativeMove>) {
            // Relative magnitude, direction from the speed's bit 15 (0 CCW = positive).
            target = motion_.position() + (speed < 0 ? -1.0 : 1.0) * command.relative;
          } else {
            target = command.position;
          }
          if (control_mode() == ControlMode::Position) {
            target = std::clamp<double>(target, get(Role::MinLimit), get(Role::MaxLimit));
          }
          put(Role::GoalPosition, std::lround(target));
          motion_.move_to(target, motion_limits(speed));
        }
      },
      *move);
  return {};
}

// --- Modbus RTU (SMSMB) -------------------------------------------------------------------

std::optional<Bytes> VirtualServo::handle_modbus(const protocol::rtu::Adu& request, Clock::time_point now) {
  update(now);
  const std::uint8_t reply_slave = id();
  const bool broadcast = request.slave == 0;
  if ((!broadcast && request.slave != reply_slave) || request.pdu.empty()) return std::nullopt;
  last_command_ = now;

  using Handler = ModbusOutcome (VirtualServo::*)(std::span<const std::uint8_t>);
  struct ModbusFunction {
    std::uint8_t code;
    bool reads;  // meaningless as broadcast: ignored there
    Handler handler;
  };
  static constexpr ModbusFunction kFunctions[] = {
      {0x03, true, &VirtualServo::on_read_holding},    {0x06, false, &VirtualServo::on_write_single},
      {0x10, false, &VirtualServo::on_write_multiple}, {0x11, true, &VirtualServo::on_report_slave_id},
      {0x41, false, &VirtualServo::on_restart},
  };
  const std::uint8_t code = request.pdu[0];
  const auto* function = std::find_if(std::begin(kFunctions), std::end(kFunctions),
                                      [code](const ModbusFunction& entry) { return entry.code == code; });
  ModbusOutcome outcome;
  if (function == std::end(kFunctions)) {
    outcome.exception = kIllegalFunction;  // FC 04 too: the real servo refuses it (docs/PROTOCOL.md §1.3)
  } else if (broadcast && function->reads) {
    return std::nullopt;
  } else {
    outcome = (this->*(function->handler))(request.pdu);
  }
  refresh_present();
  if (broadcast) return std::nullopt;
  if (outcome.exception != 0) outcome.pdu = {static_cast<std::uint8_t>(code | 0x80), outcome.exception};
  return protocol::rtu::frame(reply_slave, outcome.pdu);
}

VirtualServo::ModbusOutcome VirtualServo::on_read_holding(std::span<const std::uint8_t> pdu) {
  if (pdu.size() != 5) return {{}, kIllegalValue};
  const std::uint16_t address = be16(pdu, 1);
  const std::uint16_t quantity = be16(pdu, 3);
  if (quantity < 1 || quantity > kMaxReadRegisters) return {{}, kIllegalValue};
  if (!memory_.contains(address, quantity)) return {{}, kIllegalAddress};
  // A register that is no field is not there to read (wiki memory-smsmb lists only the
  // defined registers; the firmware answers 0x02 rather than a made-up 0).
  for (std::uint32_t reg = address; reg < std::uint32_t{address} + quantity; ++reg) {
    if (modbus_map::field_covering(*table_, static_cast<std::uint16_t>(reg)) == nullptr) return {{}, kIllegalAddress};
  }
  const auto bytes = memory_.wire(address, quantity);
  position_at_read_ = motion_.position();
  Bytes reply{0x03, static_cast<std::uint8_t>(bytes.size())};
  reply.insert(reply.end(), bytes.begin(), bytes.end());
  return {std::move(reply), 0};
}

namespace {
std::uint8_t modbus_exception_for(bool not_writable) { return not_writable ? kIllegalAddress : kIllegalValue; }
}  // namespace

VirtualServo::ModbusOutcome VirtualServo::on_write_single(std::span<const std::uint8_t> pdu) {
  if (pdu.size() != 5) return {{}, kIllegalValue};
  const WriteResult result = write_checked(be16(pdu, 1), pdu.subspan(3, 2), WriteCheck::Modbus);
  if (result != WriteResult::Ok) return {{}, modbus_exception_for(result == WriteResult::NotWritable)};
  return {Bytes(pdu.begin(), pdu.end()), 0};  // echo
}

VirtualServo::ModbusOutcome VirtualServo::on_write_multiple(std::span<const std::uint8_t> pdu) {
  if (pdu.size() < 6) return {{}, kIllegalValue};
  const std::uint16_t quantity = be16(pdu, 3);
  const std::uint8_t byte_count = pdu[5];
  if (quantity < 1 || quantity > kMaxWriteRegisters || byte_count != quantity * 2 || pdu.size() != 6U + byte_count) {
    return {{}, kIllegalValue};
  }
  const WriteResult result = write_checked(be16(pdu, 1), pdu.subspan(6), WriteCheck::Modbus);
  if (result != WriteResult::Ok) return {{}, modbus_exception_for(result == WriteResult::NotWritable)};
  return {Bytes(pdu.begin(), pdu.begin() + 5), 0};
}

VirtualServo::ModbusOutcome VirtualServo::on_report_slave_id(std::span<const std::uint8_t>) {
  // addr, 0x11, 3, addr, status H, status L (docs/PROTOCOL.md §1.3)
  const std::uint32_t status = field(Role::Status) ? memory_.raw(*field(Role::Status)) : 0;
  return {Bytes{0x11, 3, id(), static_cast<std::uint8_t>(status >> 8), static_cast<std::uint8_t>(status & 0xFF)}, 0};
}

VirtualServo::ModbusOutcome VirtualServo::on_restart(std::span<const std::uint8_t> pdu) {
  // Decision: a unicast restart is acknowledged with an echo before the servo goes deaf.
  reboot();
  return {Bytes(pdu.begin(), pdu.end()), 0};
}

// --- persistence and summaries -----------------------------------------------------------

FieldValues VirtualServo::persisted_eeprom() const {
  FieldValues values;
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area == Area::Eeprom) values.emplace(std::string(spec.name), eeprom_.raw(spec));
  }
  return values;
}

FieldValues VirtualServo::backup_eeprom() const {
  FieldValues values;
  for (const FieldSpec& spec : table_->fields) {
    if (spec.area == Area::Eeprom) values.emplace(std::string(spec.name), backup_.raw(spec));
  }
  return values;
}

std::vector<std::string> VirtualServo::load_persisted(const FieldValues& eeprom, const FieldValues& backup,
                                                      Clock::time_point now) {
  std::vector<std::string> unknown;
  const auto load = [&](const FieldValues& values, ServoMemory& image) {
    for (const auto& [name, raw] : values) {
      const FieldSpec* spec = modbus_map::field_by_name(*table_, name);
      if (spec == nullptr || spec->area != Area::Eeprom) {
        unknown.push_back(name);
        continue;
      }
      image.set_raw(*spec, raw);
    }
  };
  load(eeprom, eeprom_);
  load(backup, backup_);
  update(now);
  power_on();
  return unknown;
}

bool VirtualServo::take_persist_dirty() { return std::exchange(persist_dirty_, false); }

ServoSummary VirtualServo::summary() const {
  ServoSummary summary;
  summary.config = ServoConfig{id(), table_->id, protocol(), baud()};
  summary.offline = offline_;
  summary.present_position = get(Role::PresentPosition);
  summary.goal_position = get(Role::GoalPosition);
  summary.moving = get(Role::Moving) != 0;
  summary.move_started = move_started_;
  summary.arrived = arrived_at_;
  summary.position_at_goal = position_at_goal_;
  summary.read_before_goal = read_before_goal_;
  summary.reversed = motion_.reversed();
  summary.turned_back = motion_.turned_back();
  summary.heartbeat_stops = heartbeat_stops_;
  return summary;
}

}  // namespace sms::simulator
