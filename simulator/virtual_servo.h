#pragma once
// One simulated servo: its control table (ServoMemory), its motor (MotionModel) and its
// firmware's answers to the packet instructions of docs/PROTOCOL.md §1.1/§1.2 or the Modbus functions of
// docs/PROTOCOL.md §1.3. Not thread-safe: SimulatedBus serialises every call. Time is passed in, the
// model advances to it on each access (no thread of its own).
#include <array>
#include <chrono>
#include <cstdint>
#include <map>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "modbus_map/control_table.h"
#include "protocol/d55d.h"
#include "protocol/modbus_rtu.h"
#include "protocol/packet.h"
#include "simulator/motion_model.h"
#include "simulator/servo_memory.h"
#include "simulator/simulated_bus.h"
#include "simulator/table_behaviour.h"

namespace sms::simulator {

using Clock = std::chrono::steady_clock;

// EEPROM field values by field name, as the state file keeps them.
using FieldValues = std::map<std::string, std::uint32_t, std::less<>>;

class VirtualServo {
 public:
  // `position_skew` (position units) starts a duplicate a little apart from its twin, so
  // colliding replies differ as they would on a real bus.
  VirtualServo(const ServoConfig& config, Clock::time_point now, std::chrono::milliseconds reboot_time,
               double position_skew = 0);

  std::uint8_t id() const;
  std::uint32_t baud() const;
  protocol::BusProtocol protocol() const { return table_->protocol; }
  const modbus_map::TableSpec& table() const { return *table_; }
  // The return delay field converted to time (docs/PROTOCOL.md §5), plus any injected lateness.
  Clock::duration return_delay() const;
  Clock::duration extra_delay() const { return extra_delay_; }
  // Not offline and not rebooting.
  bool listening(Clock::time_point now) const;

  // A decoded packet addressed to this servo's ID or broadcast. Returns the status packet to
  // send, or nothing (broadcast, response level, REBOOT, SYNC WRITE, not listed in SYNC READ).
  std::optional<protocol::Packet> handle_packet(const protocol::Packet& request, Clock::time_point now);
  // d55d: a frame with this servo's ID failed its checksum; the next reply carries the bit.
  void note_checksum_error();
  // A Modbus request for this slave or broadcast (0). Returns the reply ADU (with CRC).
  std::optional<protocol::Bytes> handle_modbus(const protocol::rtu::Adu& request, Clock::time_point now);

  // Advances the motion model and refreshes the present-value fields.
  void update(Clock::time_point now);
  const ServoMemory& memory() const { return memory_; }
  // Test backdoor: writes raw wire bytes with the effects of a bus write, read-only fields too.
  bool write_raw(std::uint16_t address, std::span<const std::uint8_t> bytes, Clock::time_point now);

  // Faults
  void set_offline(bool offline) { offline_ = offline; }
  bool offline() const { return offline_; }
  void set_extra_delay(Clock::duration extra) { extra_delay_ = extra; }
  // Every reply leaves with a byte flipped: a servo whose transmitter sends garbage.
  void set_garbled(bool garbled) { garbled_ = garbled; }
  bool garbled() const { return garbled_; }
  void set_error_bits(std::uint8_t bits, Clock::time_point now);

  // Persistence (state file): the EEPROM as it would be after a power cycle, and the backup.
  FieldValues persisted_eeprom() const;
  FieldValues backup_eeprom() const;
  // Loads both and powers the servo on from them. Unknown names are returned for a warning.
  std::vector<std::string> load_persisted(const FieldValues& eeprom, const FieldValues& backup, Clock::time_point now);
  // True once after anything persisted changed.
  bool take_persist_dirty();

  ServoSummary summary() const;

 private:
  // --- packet instructions ---------------------------------------------------------------
  struct Outcome {
    bool answer = true;
    std::uint8_t error = 0;
    protocol::Bytes data;
  };
  enum class ReplyClass : std::uint8_t { Ping, Read, SyncRead, Other };
  using PacketHandler = Outcome (VirtualServo::*)(const protocol::Packet&);
  struct PacketInstruction {
    std::uint8_t code;
    ReplyClass reply;
    PacketHandler handler;
  };
  static const std::array<PacketInstruction, 12> kFeetechInstructions;
  static const std::array<PacketInstruction, 11> kD55dInstructions;

  Outcome on_ping(const protocol::Packet&);
  Outcome on_read(const protocol::Packet&);
  Outcome on_write(const protocol::Packet&);
  Outcome on_reg_write(const protocol::Packet&);
  Outcome on_action(const protocol::Packet&);
  Outcome on_sync_write(const protocol::Packet&);
  Outcome on_sync_read(const protocol::Packet&);
  Outcome on_recovery(const protocol::Packet&);
  Outcome on_reboot(const protocol::Packet&);
  Outcome on_backup(const protocol::Packet&);
  Outcome on_reset_status(const protocol::Packet&);
  Outcome on_calibrate(const protocol::Packet&);
  Outcome on_factory_reset(const protocol::Packet&);
  Outcome on_start_end(const protocol::Packet&);
  Outcome on_trajectory_write(const protocol::Packet&);
  Outcome on_trajectory_action(const protocol::Packet&);
  Outcome on_custom(const protocol::Packet&);
  bool answers(ReplyClass reply, bool broadcast) const;

  // --- Modbus functions --------------------------------------------------------------------
  struct ModbusOutcome {
    protocol::Bytes pdu;  // reply PDU when exception == 0
    std::uint8_t exception = 0;
  };
  ModbusOutcome on_read_holding(std::span<const std::uint8_t> pdu);
  ModbusOutcome on_write_single(std::span<const std::uint8_t> pdu);
  ModbusOutcome on_write_multiple(std::span<const std::uint8_t> pdu);
  ModbusOutcome on_report_slave_id(std::span<const std::uint8_t> pdu);
  ModbusOutcome on_restart(std::span<const std::uint8_t> pdu);

  // --- table access --------------------------------------------------------------------------
  enum class WriteResult : std::uint8_t { Ok, NotWritable, BadValue };
  enum class WriteCheck : std::uint8_t {
    Bus,       // packet WRITE: read-only fields refused, bytes of no field ignored
    Modbus,    // FC 06/10: also refused when an address is no field's first
    DryRun,    // REG WRITE: check as Bus, write nothing
    Backdoor,  // tests: anything inside the table
  };
  WriteResult write_checked(std::uint16_t address, std::span<const std::uint8_t> bytes, WriteCheck check);
  const modbus_map::FieldSpec* field(Role role) const { return fields_[static_cast<std::size_t>(role)]; }
  std::optional<Role> role_of(const modbus_map::FieldSpec& spec) const;
  std::int32_t get(Role role, std::int32_t fallback = 0) const;
  void put(Role role, std::int64_t value);
  bool eeprom_unlocked() const;
  void persist(const modbus_map::FieldSpec& spec);

  // --- behaviour -----------------------------------------------------------------------------
  void power_on();
  void reboot();
  void apply_written(const ServoMemory& before, std::span<const modbus_map::FieldSpec* const> written);
  void advance_motion(double seconds);
  void next_trajectory_point();
  void normalise_single_turn();
  void drive_from_table(bool goal_written);
  void calibrate(std::int32_t present);
  void start_homing();
  void stop_homing(std::uint8_t status);
  void on_arrival();
  void stop_commands();  // trajectory and homing end
  void refresh_present();
  double load_permille() const;  // signed, 0.1 % of full torque
  bool heartbeat_armed() const;
  ControlMode control_mode() const;
  bool multi_turn() const;
  bool torque_on() const;
  double degrees_per_unit() const;
  double units(double degrees) const { return degrees / degrees_per_unit(); }
  MotionLimits motion_limits(std::int32_t speed_field_value) const;
  double speed_units(std::int32_t speed_field_value) const;  // signed units/s, 0 = maximum applied
  // The speed fields' unit; sts: chosen by the phase byte.
  double degrees_per_s_per_speed_unit() const;
  std::uint8_t error_bits() const;

  const modbus_map::TableSpec* table_;
  const TableBehaviour* behaviour_;
  ServoMemory memory_;
  ServoMemory eeprom_;  // EEPROM fields as they survive a power cycle
  ServoMemory backup_;  // BACKUP / RECOVERY image
  std::array<const modbus_map::FieldSpec*, static_cast<std::size_t>(Role::Count)> fields_{};
  MotionModel motion_;
  Clock::time_point clock_;
  // The last goal written in position mode, and when the motor reached it (the arrival of a
  // timed group move: tests and bench/timed_moves measure these).
  std::optional<Clock::time_point> move_started_;
  std::optional<Clock::time_point> arrived_at_;
  double position_at_goal_ = 0;  // where the motor was when that goal was written (a stop's run-on)
  // Where the motor was when it last answered a read, and that as of the last goal write: a stop
  // computed from that read cannot know how far the axis ran on while the host held its frame.
  double position_at_read_ = 0;
  double read_before_goal_ = 0;
  Clock::time_point last_command_;
  std::uint64_t heartbeat_stops_ = 0;  // times the d55d heartbeat stopped the motor (motion ID)
  Clock::time_point deaf_until_;
  std::chrono::milliseconds reboot_time_;
  double temperature_ = 28.0;
  double accumulated_ = 0;  // d55d accumulated angle, position units

  struct PendingWrite {
    std::uint16_t address;
    protocol::Bytes data;
  };
  std::optional<PendingWrite> reg_write_;
  std::vector<protocol::d55d::TrajectoryPoint> trajectory_;
  std::optional<std::size_t> trajectory_next_;

  enum class HomingPhase : std::uint8_t { Idle, SeekZero, SeekEnd };
  HomingPhase homing_phase_ = HomingPhase::Idle;
  std::uint8_t homing_status_ = 0;  // high nibble of address 24: 0 idle, 1 running, 2 done, 3 failed
  double cw_switch_ = 0;            // photo-switch positions, position units
  double ccw_switch_ = 0;
  double zero_switch_ = 0;
  double end_switch_ = 0;

  bool offline_ = false;
  Clock::duration extra_delay_{};
  bool garbled_ = false;
  std::uint8_t injected_errors_ = 0;
  std::uint8_t pending_error_ = 0;  // d55d checksum bit, shown once
  bool persist_dirty_ = false;
};

}  // namespace sms::simulator
