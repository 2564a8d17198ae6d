#pragma once
// Table `d55d`: the D5 5D vendor protocol's table, doc 002 ch. 3, docs/PROTOCOL.md §2.3. Byte addresses,
// low byte first. Positions count degrees × angle_resolution (13, unit 0.1°).
#include <array>

#include "modbus_map/tables/common.h"

namespace sms::modbus_map::tables {

// Designated initializers leave the fields a row does not name at their defaults, on purpose.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
inline constexpr std::array kD55dFields{
    FieldSpec{.addr = 0, .name = "vendor_code", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax},
    FieldSpec{.addr = 2, .name = "software_version", .size = 1, .access = R, .area = Eeprom, .max = kReadByteMax},
    FieldSpec{.addr = 3, .name = "id", .size = 1, .access = RW, .area = Eeprom, .default_value = 1, .max = 253,
              .notes = "254 is the broadcast ID"},
    FieldSpec{.addr = 4, .name = "baud_rate", .size = 1, .access = RW, .area = Eeprom, .default_value = 0, .max = 10,
              .notes = "code of the d55d baud table (docs/PROTOCOL.md §3); 0: 115200 base motors, 9600 others"},
    FieldSpec{.addr = 5, .name = "return_delay", .size = 1, .access = RW, .area = Eeprom, .default_value = 16,
              .max = kByteMax, .unit = "500 µs", .notes = "default 8 on base motors"},
    FieldSpec{.addr = 6, .name = "cw_angle_limit", .size = 2, .access = RW, .area = Eeprom, .default_value = 0,
              .max = kWordMax, .unit = "deg × resolution", .notes = "both limits 0: speed (wheel) mode"},
    FieldSpec{.addr = 8, .name = "ccw_angle_limit", .size = 2, .access = RW, .area = Eeprom, .max = kWordMax,
              .unit = "deg × resolution", .notes = "default: the motor's max angle × resolution"},
    FieldSpec{.addr = 11, .name = "max_temperature", .size = 1, .access = RW, .area = Eeprom, .default_value = 80,
              .encoding = sign_magnitude(7), .min = -sign_magnitude_max(7), .max = sign_magnitude_max(7),
              .unit = "°C"},
    FieldSpec{.addr = 12, .name = "max_current", .size = 1, .access = RW, .area = Eeprom, .max = kByteMax,
              .unit = "0.1 A"},
    FieldSpec{.addr = 13, .name = "angle_resolution", .size = 1, .access = RW, .area = Eeprom, .default_value = 10,
              .min = 1, .max = kByteMax, .unit = "0.1°"},
    FieldSpec{.addr = 16, .name = "response_level", .size = 1, .access = RW, .area = Eeprom, .default_value = 2,
              .max = 2, .notes = "0 never, 1 READ only, 2 all except broadcast"},
    FieldSpec{.addr = 17, .name = "heartbeat_enable", .size = 1, .access = RW, .area = Eeprom, .default_value = 1,
              .max = 1, .notes = "500 ms without a command -> the motor stops"},
    FieldSpec{.addr = 18, .name = "unload_conditions", .size = 1, .access = RW, .area = Eeprom,
              .default_value = 0x7F, .max = kByteMax, .notes = "bits as the ERROR byte"},
    FieldSpec{.addr = 19, .name = "photo_switch_zero_direction", .size = 1, .access = W, .area = Eeprom, .min = 1,
              .max = 2, .notes = "1 CW, 2 CCW"},
    FieldSpec{.addr = 20, .name = "rs485_termination", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 1},
    FieldSpec{.addr = 21, .name = "base_acceleration", .size = 1, .access = RW, .area = Eeprom, .default_value = 36,
              .max = kByteMax, .unit = "10 °/s²"},
    FieldSpec{.addr = 22, .name = "base_deceleration", .size = 1, .access = RW, .area = Eeprom, .default_value = 36,
              .max = kByteMax, .unit = "10 °/s²"},
    FieldSpec{.addr = 24, .name = "photo_switch_homing", .size = 1, .access = RW, .area = Eeprom, .default_value = 0,
              .max = 1,
              .notes = "write 0 stop / 1 start; reads high nibble 0 idle, 1 running, 2 done, 3 failed"},
    FieldSpec{.addr = 25, .name = "clear_unload_condition", .size = 1, .access = W, .area = Eeprom,
              .max = kByteMax},
    FieldSpec{.addr = 30, .name = "goal_position", .size = 2, .access = RW, .area = Ram, .max = kWordMax,
              .unit = "deg × resolution", .notes = "base motors: relative"},
    FieldSpec{.addr = 32, .name = "run_speed", .size = 2, .access = RW, .area = Ram, .default_value = 0,
              .encoding = sign_magnitude(15), .min = -sign_magnitude_max(15), .max = sign_magnitude_max(15),
              .notes = "bit 15 set = CW; 0 = stop without torque"},
    FieldSpec{.addr = 34, .name = "acceleration", .size = 1, .access = RW, .area = Ram, .default_value = 36,
              .max = kByteMax, .unit = "10 °/s²"},
    FieldSpec{.addr = 35, .name = "deceleration", .size = 1, .access = RW, .area = Ram, .default_value = 36,
              .max = kByteMax, .unit = "10 °/s²"},
    FieldSpec{.addr = 36, .name = "present_position", .size = 2, .access = R, .area = Ram, .max = kWordMax,
              .unit = "deg × resolution", .notes = "finger/wrist motors only"},
    FieldSpec{.addr = 38, .name = "present_speed", .size = 2, .access = R, .area = Ram, .encoding = kTwosComplement,
              .min = kInt16Min, .max = kInt16Max},
    FieldSpec{.addr = 40, .name = "accumulated_angle", .size = 2, .access = R, .area = Ram, .default_value = 0,
              .encoding = kTwosComplement, .min = kInt16Min, .max = kInt16Max, .notes = "wraps"},
    FieldSpec{.addr = 42, .name = "moving", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .bit_space = BitSpace::DiscreteInput},
    FieldSpec{.addr = 43, .name = "brake", .size = 1, .access = RW, .area = Ram, .default_value = 0, .max = 1,
              .bit_space = BitSpace::Coil},
    FieldSpec{.addr = 44, .name = "reg_write_flag", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .bit_space = BitSpace::DiscreteInput,
              .notes = "1 while a REG WRITE waits for ACTION"},
    FieldSpec{.addr = 46, .name = "present_temperature", .size = 1, .access = R, .area = Ram,
              .encoding = sign_magnitude(7), .min = -sign_magnitude_max(7), .max = sign_magnitude_max(7),
              .unit = "°C"},
    FieldSpec{.addr = 47, .name = "sleep", .size = 1, .access = RW, .area = Ram, .default_value = 0, .max = 1,
              .bit_space = BitSpace::Coil},
    FieldSpec{.addr = 48, .name = "photo_switch_state", .size = 1, .access = R, .area = Ram, .default_value = 0,
              .max = kReadByteMax, .notes = "bit0 switch 1, bit1 switch 2"},
    FieldSpec{.addr = 49, .name = "move_without_photo_coupler", .size = 1, .access = RW, .area = Ram,
              .default_value = 0, .max = 1},
};
static_assert(fields_sorted_and_disjoint(kD55dFields, Addressing::Byte), "d55d: fields overlap or are out of order");
static_assert(fields_well_formed(kD55dFields), "d55d: a field's range, default or name is inconsistent");

#pragma GCC diagnostic pop

}  // namespace sms::modbus_map::tables
