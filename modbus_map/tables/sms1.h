#pragma once
// Table `sms1`: SMS 1.0, doc 000, docs/PROTOCOL.md §2.2. Byte addresses, low byte first by default (the
// printed defaults read high byte first; docs/PROTOCOL.md §2.2 decision).
#include <array>

#include "modbus_map/tables/common.h"

namespace sms::modbus_map::tables {

// Designated initializers leave the fields a row does not name at their defaults, on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
inline constexpr std::array kSms1Fields{
    FieldSpec{.addr = 3, .name = "software_version", .size = 2, .access = R, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 5, .name = "id", .size = 1, .access = RW, .area = Eeprom, .default_value = 0, .max = 253,
              .notes = "254 is the broadcast ID"},
    FieldSpec{.addr = 6, .name = "baud_rate", .size = 1, .access = RW, .area = Eeprom, .default_value = 0, .max = 7,
              .notes = "code of the feetech baud table (docs/PROTOCOL.md §3); out-of-table codes fall back to 1 M"},
    FieldSpec{.addr = 7, .name = "return_delay", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax, .unit = "2 µs"},
    FieldSpec{.addr = 8, .name = "response_level", .size = 1, .access = RW, .area = Eeprom, .default_value = 1,
              .max = 1, .notes = "0: only READ and PING answered; 1: every instruction"},
    FieldSpec{.addr = 9, .name = "min_angle_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 4095, .unit = "steps", .notes = "goal clamped into [min, max]"},
    FieldSpec{.addr = 11, .name = "max_angle_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 4095,
              .max = 4095, .unit = "steps"},
    FieldSpec{.addr = 13, .name = "max_temperature", .size = 1, .access = RW, .area = Eeprom, .default_value = 80,
              .max = kByteMax, .unit = "°C"},
    FieldSpec{.addr = 14, .name = "max_input_voltage", .size = 1, .access = RW, .area = Eeprom, .default_value = 140,
              .max = kByteMax, .unit = "0.1 V"},
    FieldSpec{.addr = 15, .name = "min_input_voltage", .size = 1, .access = RW, .area = Eeprom, .default_value = 60,
              .max = kByteMax, .unit = "0.1 V"},
    FieldSpec{.addr = 16, .name = "max_torque", .size = 2, .access = RW, .area = Eeprom, .default_value = 1000,
              .max = 1000, .unit = "0.1 %", .notes = "1000 = maximum"},
    FieldSpec{.addr = 18, .name = "pwm_phase_mode", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 19, .name = "unload_conditions", .size = 1, .access = RW, .area = Eeprom, .default_value = 47,
              .max = kByteMax, .notes = "bits as error (65)"},
    FieldSpec{.addr = 20, .name = "led_alarm_conditions", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 47, .max = kByteMax, .notes = "bits as error (65); 0: LED off"},
    FieldSpec{.addr = 21, .name = "p_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 15,
              .max = kByteMax},
    FieldSpec{.addr = 22, .name = "d_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 23, .name = "i_gain", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 24, .name = "min_pwm", .size = 2, .access = RW, .area = Eeprom, .max = kWordMax},
    FieldSpec{.addr = 26, .name = "cw_insensitive_zone", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 1, .max = kByteMax, .unit = "0.087°"},
    FieldSpec{.addr = 27, .name = "ccw_insensitive_zone", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 1, .max = kByteMax, .unit = "0.087°"},
    FieldSpec{.addr = 28, .name = "integral_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kWordMax},
    FieldSpec{.addr = 30, .name = "differential_sampling_factor", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 0, .max = kByteMax},
    FieldSpec{.addr = 31, .name = "torque_step", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 32, .name = "position_step", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kByteMax},
    FieldSpec{.addr = 33, .name = "position_correction", .size = 2, .access = RW, .area = Eeprom,
              .default_value = 0, .encoding = sign_magnitude(11), .min = -sign_magnitude_max(11),
              .max = sign_magnitude_max(11), .unit = "steps", .notes = "2048-4095 on the bus = negative"},
    FieldSpec{.addr = 35, .name = "operating_mode", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 2, .notes = "0 servo, 1 motor speed (run_speed), 2 torque (run_time)"},
    // Feetech's SMSCL SDK names 36-37 one two-byte maximum current (MAX_CURRENT_L/H); doc 000
    // prints one byte with default 7. Two bytes, so a write of 36-37 lands whole.
    FieldSpec{.addr = 36, .name = "protection_current", .size = 2, .access = RW, .area = Eeprom, .default_value = 7,
              .max = kWordMax, .notes = "two bytes, as Feetech's SMSCL SDK (MAX_CURRENT 36-37)"},
    // 128 = mid-point calibration on older SMS firmware (docs/PROTOCOL.md §1.1, CALIBRATE).
    FieldSpec{.addr = 40, .name = "torque_switch", .size = 1, .access = RW, .area = Ram, .default_value = 0,
              .max = 128, .bit_space = BitSpace::Coil, .notes = "0 off, 1 on, 128 = calibrate to 2048 (docs/PROTOCOL.md §1.1)",
              .allowed_values = kTorqueEnableValues},
    // Not in doc 000; Feetech's SMSCL SDK writes 7 bytes from 41 (ACC, position, time, speed).
    FieldSpec{.addr = 41, .name = "acceleration", .size = 1, .access = RW, .area = Ram, .default_value = 0,
              .max = kByteMax, .unit = "100 steps/s²", .notes = "0 = maximum; from Feetech's SMSCL SDK"},
    FieldSpec{.addr = 42, .name = "goal_position", .size = 2, .access = RW, .area = Ram, .max = 4095,
              .unit = "steps", .notes = "0-4095 = 0-360°"},
    FieldSpec{.addr = 44, .name = "run_time", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .encoding = sign_magnitude(10), .min = -1000, .max = 1000, .unit = "ms / 0.1 %",
              .notes = "mode 0: move time, 0 = fastest; mode 2: signed torque"},
    FieldSpec{.addr = 46, .name = "run_speed", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .unit = "0.087°/s", .notes = "wins over run_time; mode 1: signed speed"},
    FieldSpec{.addr = 48, .name = "lock", .size = 1, .access = RW, .area = Ram, .default_value = 0, .max = 1,
              .bit_space = BitSpace::Coil, .notes = "0: EEPROM writes persist (slow, wears EEPROM)"},
    FieldSpec{.addr = 56, .name = "present_position", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .unit = "steps", .notes = "bit 15 direction, as Feetech's SMSCL SDK decodes it"},
    FieldSpec{.addr = 58, .name = "present_speed", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .unit = "0.087°/s"},
    FieldSpec{.addr = 60, .name = "present_load", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(10), .min = -sign_magnitude_max(10), .max = sign_magnitude_max(10),
              .unit = "0.1 %", .notes = "0-1000, bit 10 direction (Feetech's SMSCL SDK)"},
    FieldSpec{.addr = 62, .name = "present_voltage", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .unit = "0.1 V"},
    FieldSpec{.addr = 63, .name = "present_temperature", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .unit = "°C"},
    FieldSpec{.addr = 64, .name = "reg_write_flag", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .notes = "1 while a REG WRITE waits for ACTION"},
    FieldSpec{.addr = 65, .name = "error", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .notes = "bit0 voltage, 1 angle sensor, 2 over-temperature, 3 over-current, 5 overload"},
    FieldSpec{.addr = 66, .name = "moving", .size = 1, .access = R, .area = Ram, .max = kReadByteMax,
              .bit_space = BitSpace::DiscreteInput},
    FieldSpec{.addr = 67, .name = "present_goal_position", .size = 2, .access = R, .area = Ram, .max = kWordMax,
              .unit = "steps"},
    FieldSpec{.addr = 69, .name = "present_current", .size = 2, .access = R, .area = Ram,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15)},
};
static_assert(fields_sorted_and_disjoint(kSms1Fields, Addressing::Byte), "sms1: fields overlap or are out of order");
static_assert(fields_well_formed(kSms1Fields), "sms1: a field's range, default or name is inconsistent");

#pragma GCC diagnostic pop

}  // namespace sms::modbus_map::tables
