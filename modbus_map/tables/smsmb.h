#pragma once
// Table `smsmb`: Feetech's Modbus-RTU servo firmware (SMSMB), docs/PROTOCOL.md §2.4, with the factory area
// 0x180-0x196 named after Feetech's wiki page `memory-smsmb` (section "出厂参数"). One 16-bit
// register per field, high byte first; signed values are two's complement (docs/PROTOCOL.md §1.3 decision).
#include <array>

#include "modbus_map/tables/common.h"

namespace sms::modbus_map::tables {

// Designated initializers leave the fields a row does not name at their defaults, on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
// Lock: 0 EEPROM writes persist, 1 they do not, 128 unlocks the factory area (0x180-).
inline constexpr std::array<std::int32_t, 3> kSmsmbLockValues{0, 1, 128};
// Mode 2 is reserved on SMSMB.
inline constexpr std::array<std::int32_t, 4> kSmsmbModeValues{0, 1, 3, 4};

inline constexpr std::array kSmsmbFields{
    FieldSpec{.addr = 0x00, .name = "firmware_version", .size = 2, .access = R, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x01, .name = "servo_version", .size = 2, .access = R, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x02, .name = "firmware_year", .size = 2, .access = R, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x03, .name = "firmware_month", .size = 2, .access = R, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x0A, .name = "id", .size = 2, .access = RW, .area = Eeprom, .default_value = 1, .min = 1,
              .max = 247, .notes = "Modbus slave address; 0 is broadcast"},
    FieldSpec{.addr = 0x0B, .name = "baud_rate", .size = 2, .access = RW, .area = Eeprom, .default_value = 2,
              .max = 9, .notes = "code of the modbus-rtu baud table (docs/PROTOCOL.md §3)"},
    FieldSpec{.addr = 0x0C, .name = "return_delay", .size = 2, .access = RW, .area = Eeprom, .default_value = 500,
              .max = 500, .unit = "µs"},
    FieldSpec{.addr = 0x0D, .name = "min_angle_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 4095, .unit = "steps", .notes = "0 with max 0: multi-turn"},
    FieldSpec{.addr = 0x0E, .name = "max_angle_limit", .size = 2, .access = RW, .area = Eeprom,
              .default_value = 4095, .max = 4095, .unit = "steps"},
    FieldSpec{.addr = 0x0F, .name = "position_calibration", .size = 2, .access = RW, .area = Eeprom,
              .default_value = 0, .encoding = kTwosComplement, .min = -2047, .max = 2047, .unit = "steps",
              .notes = "fault_reset bit 2 stores the centre offset here"},
    FieldSpec{.addr = 0x10, .name = "mode", .size = 2, .access = RW, .area = Eeprom, .default_value = 0, .max = 4,
              .notes = "0 servo, 1 constant speed, 3 torque off on arrival, 4 stepper (2 reserved)",
              .allowed_values = kSmsmbModeValues},
    FieldSpec{.addr = 0x11, .name = "position_p_gain", .size = 2, .access = RW, .area = Eeprom, .max = kByteMax},
    FieldSpec{.addr = 0x12, .name = "position_d_gain", .size = 2, .access = RW, .area = Eeprom, .max = kByteMax},
    FieldSpec{.addr = 0x13, .name = "position_i_gain", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 0x14, .name = "speed_p_gain", .size = 2, .access = RW, .area = Eeprom, .max = kByteMax,
              .notes = "constant-speed mode"},
    FieldSpec{.addr = 0x15, .name = "speed_i_gain", .size = 2, .access = RW, .area = Eeprom, .max = kByteMax,
              .notes = "constant-speed mode"},
    FieldSpec{.addr = 0x80, .name = "goal_position", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "steps"},
    FieldSpec{.addr = 0x81, .name = "torque_switch", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .max = 1, .bit_space = BitSpace::Coil},
    FieldSpec{.addr = 0x82, .name = "acceleration", .size = 2, .access = RW, .area = Ram, .max = kWordMax,
              .unit = "8.79 °/s²", .notes = "0 = maximum; power-on value from 0x195"},
    // Signed like every SMSMB value with a direction (docs/PROTOCOL.md §1.3); the wiki prints 0-65535.
    FieldSpec{.addr = 0x83, .name = "running_speed", .size = 2, .access = RW, .area = Ram,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "0.732 rpm",
              .notes = "power-on value from 0x196"},
    FieldSpec{.addr = 0x84, .name = "torque_limit", .size = 2, .access = RW, .area = Ram, .default_value = 1000,
              .max = 1000, .unit = "0.1 %", .notes = "power-on value from 0x194"},
    FieldSpec{.addr = 0x85, .name = "lock", .size = 2, .access = RW, .area = Ram, .default_value = 1, .max = 128,
              .notes = "0 EEPROM writes persist, 1 they do not, 128 unlocks the factory area",
              .allowed_values = kSmsmbLockValues},
    FieldSpec{.addr = 0x86, .name = "fault_reset", .size = 2, .access = W, .area = Ram, .default_value = 0,
              .max = 255,
              .notes = "bit0 overload, 1 over-current, 2 set centre (2048), 5 voltage, 6 overheat, 7 encoder"},
    FieldSpec{.addr = 0x100, .name = "status", .size = 2, .access = R, .area = Ram, .default_value = 0,
              .max = kWordMax,
              .notes = "bit0 voltage, 1 encoder, 2 temperature, 3 current, 4 torque on, 5 load"},
    FieldSpec{.addr = 0x101, .name = "present_position", .size = 2, .access = R, .area = Ram,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "steps"},
    FieldSpec{.addr = 0x102, .name = "present_speed", .size = 2, .access = R, .area = Ram,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "0.732 rpm"},
    FieldSpec{.addr = 0x103, .name = "output_pwm", .size = 2, .access = R, .area = Ram,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "0.1 %"},
    FieldSpec{.addr = 0x104, .name = "present_voltage", .size = 2, .access = R, .area = Ram, .max = kWordMax,
              .unit = "0.1 V"},
    FieldSpec{.addr = 0x105, .name = "present_temperature", .size = 2, .access = R, .area = Ram, .max = kWordMax,
              .unit = "°C"},
    FieldSpec{.addr = 0x106, .name = "moving", .size = 2, .access = R, .area = Ram, .default_value = 0,
              .max = kWordMax, .bit_space = BitSpace::DiscreteInput},
    FieldSpec{.addr = 0x107, .name = "present_current", .size = 2, .access = R, .area = Ram,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .unit = "6.5 mA"},
    // Factory area: writable only after lock = 128; the servo's power-on defaults.
    FieldSpec{.addr = 0x180, .name = "moving_threshold", .size = 2, .access = RW, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x181, .name = "d_control_time", .size = 2, .access = RW, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 0x182, .name = "max_speed_limit", .size = 2, .access = RW, .area = Eeprom, .max = kInt16Max,
              .unit = "0.732 rpm"},
    FieldSpec{.addr = 0x183, .name = "h_bridge_dead_time", .size = 2, .access = RW, .area = Eeprom,
              .max = kWordMax},
    FieldSpec{.addr = 0x184, .name = "acceleration_limit", .size = 2, .access = RW, .area = Eeprom,
              .max = kWordMax, .unit = "8.79 °/s²"},
    FieldSpec{.addr = 0x185, .name = "startup_torque", .size = 2, .access = RW, .area = Eeprom, .max = 1000,
              .unit = "0.1 %"},
    FieldSpec{.addr = 0x186, .name = "cw_dead_band", .size = 2, .access = RW, .area = Eeprom, .max = 32,
              .unit = "steps"},
    FieldSpec{.addr = 0x187, .name = "ccw_dead_band", .size = 2, .access = RW, .area = Eeprom, .max = 32,
              .unit = "steps"},
    FieldSpec{.addr = 0x188, .name = "phase", .size = 2, .access = RW, .area = Eeprom, .max = 255,
              .notes = "special; do not change without need"},
    FieldSpec{.addr = 0x189, .name = "unload_conditions", .size = 2, .access = RW, .area = Eeprom, .max = 255,
              .notes = "protection switches, bits as status"},
    FieldSpec{.addr = 0x18A, .name = "led_alarm_conditions", .size = 2, .access = RW, .area = Eeprom, .max = 255,
              .notes = "bits as status"},
    FieldSpec{.addr = 0x18B, .name = "max_temperature", .size = 2, .access = RW, .area = Eeprom, .max = 100,
              .unit = "°C"},
    FieldSpec{.addr = 0x18C, .name = "max_input_voltage", .size = 2, .access = RW, .area = Eeprom, .max = 360,
              .unit = "0.1 V"},
    FieldSpec{.addr = 0x18D, .name = "min_input_voltage", .size = 2, .access = RW, .area = Eeprom, .max = 360,
              .unit = "0.1 V"},
    FieldSpec{.addr = 0x18E, .name = "overload_current", .size = 2, .access = RW, .area = Eeprom, .max = 511,
              .unit = "6.5 mA"},
    FieldSpec{.addr = 0x18F, .name = "overcurrent_protection_time", .size = 2, .access = RW, .area = Eeprom,
              .max = 5000, .unit = "ms"},
    FieldSpec{.addr = 0x190, .name = "protection_torque", .size = 2, .access = RW, .area = Eeprom, .max = 1000,
              .unit = "0.1 %", .notes = "output torque once overload protection trips"},
    FieldSpec{.addr = 0x191, .name = "overload_torque", .size = 2, .access = RW, .area = Eeprom, .max = 1000,
              .unit = "0.1 %"},
    FieldSpec{.addr = 0x192, .name = "overload_protection_time", .size = 2, .access = RW, .area = Eeprom,
              .max = 5000, .unit = "ms"},
    FieldSpec{.addr = 0x193, .name = "angle_resolution", .size = 2, .access = RW, .area = Eeprom,
              .default_value = 1, .min = 1, .max = 128},
    FieldSpec{.addr = 0x194, .name = "torque_limit_default", .size = 2, .access = RW, .area = Eeprom,
              .default_value = 1000, .max = 1000, .unit = "0.1 %"},
    FieldSpec{.addr = 0x195, .name = "acceleration_default", .size = 2, .access = RW, .area = Eeprom,
              .max = kWordMax, .unit = "8.79 °/s²"},
    FieldSpec{.addr = 0x196, .name = "speed_default", .size = 2, .access = RW, .area = Eeprom, .max = kInt16Max,
              .unit = "0.732 rpm"},
};
static_assert(fields_sorted_and_disjoint(kSmsmbFields, Addressing::Register),
              "smsmb: registers overlap or are out of order");
static_assert(fields_well_formed(kSmsmbFields), "smsmb: a field's range, default or name is inconsistent");

#pragma GCC diagnostic pop

}  // namespace sms::modbus_map::tables
