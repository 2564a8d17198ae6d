#pragma once
// Table `scs`: Feetech SCS servos (SCSCL line), the series doc 001 names beside STS/SMS. The
// layout is Feetech's own SCSCL SDK (FTServo_Linux src/SCSCL.h, FTServo_Python scscl.py):
// byte addresses, two-byte fields HIGH byte first (the SDK's End = 1), 10-bit positions, no
// acceleration, offset, calibration or mode byte; both angle limits 0 select the open-loop
// motor (PWM) mode, the PWM duty then goes to 44 with direction bit 10. Names follow `sts` where
// the meaning is the same. Decisions in docs/DECISIONS.md "Vendor fidelity".
#include <array>

#include "modbus_map/tables/common.h"

namespace sms::modbus_map::tables {

// Designated initializers leave the fields a row does not name at their defaults, on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
inline constexpr std::int32_t kScsPositionMax = 1023;

inline constexpr std::array kScsFields{
    FieldSpec{.addr = 0, .name = "firmware_major", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax},
    FieldSpec{.addr = 1, .name = "firmware_minor", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax},
    FieldSpec{.addr = 2, .name = "byte_order_flag", .size = 1, .access = R, .area = Eeprom, .default_value = 1,
              .max = kReadByteMax, .notes = "1: two-byte fields high byte first (SCS); STS/SMS show 0"},
    FieldSpec{.addr = 3, .name = "model_major", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax,
              .notes = "3-4 are the model number, high byte (3) first"},
    FieldSpec{.addr = 4, .name = "model_minor", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax},
    FieldSpec{.addr = 5, .name = "id", .size = 1, .access = RW, .area = Eeprom, .default_value = 1, .max = 253,
              .notes = "254 is the broadcast ID"},
    FieldSpec{.addr = 6, .name = "baud_rate", .size = 1, .access = RW, .area = Eeprom, .default_value = 0, .max = 7,
              .notes = "code of the feetech baud table (docs/PROTOCOL.md §3), 0-7 only"},
    FieldSpec{.addr = 7, .name = "return_delay", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax, .unit = "2 µs"},
    FieldSpec{.addr = 8, .name = "response_level", .size = 1, .access = RW, .area = Eeprom, .default_value = 1,
              .max = 1, .notes = "0: only READ and PING answered; 1: every instruction"},
    FieldSpec{.addr = 9, .name = "min_angle_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kScsPositionMax, .unit = "steps", .notes = "0 with max 0: open-loop motor (PWM) mode"},
    FieldSpec{.addr = 11, .name = "max_angle_limit", .size = 2, .access = RW, .area = Eeprom,
              .default_value = kScsPositionMax, .max = kScsPositionMax, .unit = "steps"},
    FieldSpec{.addr = 13, .name = "max_temperature", .size = 1, .access = RW, .area = Eeprom, .default_value = 70,
              .max = 100, .unit = "°C"},
    FieldSpec{.addr = 14, .name = "max_input_voltage", .size = 1, .access = RW, .area = Eeprom, .default_value = 90,
              .max = kByteMax, .unit = "0.1 V"},
    FieldSpec{.addr = 15, .name = "min_input_voltage", .size = 1, .access = RW, .area = Eeprom, .default_value = 40,
              .max = kByteMax, .unit = "0.1 V"},
    FieldSpec{.addr = 16, .name = "max_torque", .size = 2, .access = RW, .area = Eeprom, .default_value = 1000,
              .max = 1000, .unit = "0.1 %"},
    FieldSpec{.addr = 19, .name = "unload_conditions", .size = 1, .access = RW, .area = Eeprom, .default_value = 37,
              .max = kByteMax, .notes = "bits as status (65)"},
    FieldSpec{.addr = 20, .name = "led_alarm_conditions", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 37, .max = kByteMax, .notes = "bits as status (65)"},
    FieldSpec{.addr = 21, .name = "p_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 15,
              .max = kByteMax},
    FieldSpec{.addr = 22, .name = "d_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 23, .name = "i_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 24, .name = "min_startup_force", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 1000, .unit = "0.1 %"},
    FieldSpec{.addr = 26, .name = "cw_dead_band", .size = 1, .access = RW, .area = Eeprom, .default_value = 1,
              .max = 16, .unit = "steps"},
    FieldSpec{.addr = 27, .name = "ccw_dead_band", .size = 1, .access = RW, .area = Eeprom, .default_value = 1,
              .max = 16, .unit = "steps"},
    FieldSpec{.addr = 40, .name = "torque_enable", .size = 1, .access = RW, .area = Ram, .default_value = 0,
              .max = 2, .bit_space = BitSpace::Coil, .notes = "0 off, 1 on, 2 damping (free but braked)",
              .allowed_values = kTorqueSwitchWithDampingValues},
    FieldSpec{.addr = 42, .name = "goal_position", .size = 2, .access = RW, .area = Ram, .max = kScsPositionMax,
              .unit = "steps", .notes = "clamped into the angle limits"},
    FieldSpec{.addr = 44, .name = "goal_time", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .encoding = sign_magnitude(10), .min = -1000, .max = 1000, .unit = "ms or 0.1 %",
              .notes = "position mode: move time (0 = by goal_speed); motor mode: signed PWM duty"},
    FieldSpec{.addr = 46, .name = "goal_speed", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .max = kInt16Max, .unit = "steps/s", .notes = "0 = maximum speed"},
    FieldSpec{.addr = 48, .name = "lock", .size = 1, .access = RW, .area = Ram, .default_value = 1, .max = 1,
              .bit_space = BitSpace::Coil, .notes = "0: EEPROM writes persist; 1: lost at power-off"},
    FieldSpec{.addr = 56, .name = "present_position", .size = 2, .access = R, .area = Ram, .max = kWordMax,
              .unit = "steps"},
    FieldSpec{.addr = 58, .name = "present_speed", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .unit = "steps/s"},
    FieldSpec{.addr = 60, .name = "present_load", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(10), .min = -sign_magnitude_max(10), .max = sign_magnitude_max(10),
              .unit = "0.1 %"},
    FieldSpec{.addr = 62, .name = "present_voltage", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .unit = "0.1 V"},
    FieldSpec{.addr = 63, .name = "present_temperature", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .unit = "°C"},
    FieldSpec{.addr = 64, .name = "reg_write_flag", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .notes = "1 while a REG WRITE waits for ACTION"},
    FieldSpec{.addr = 65, .name = "status", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .notes = "bit0 voltage, 1 angle sensor, 2 temperature, 3 current, 5 overload"},
    FieldSpec{.addr = 66, .name = "moving", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .bit_space = BitSpace::DiscreteInput, .notes = "1 while moving"},
    FieldSpec{.addr = 69, .name = "present_current", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .unit = "6.5 mA"},
};
static_assert(fields_sorted_and_disjoint(kScsFields, Addressing::Byte), "scs: fields overlap or are out of order");
static_assert(fields_well_formed(kScsFields), "scs: a field's range, default or name is inconsistent");

#pragma GCC diagnostic pop

}  // namespace sms::modbus_map::tables
