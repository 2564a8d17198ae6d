// Every rejection the loader makes: the exact message and where it points (line:column).
#include <gtest/gtest.h>

#include <string>
#include <string_view>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;

// ---- YAML itself ----

TEST(ConfigErrors, SyntaxErrorNamesLineAndColumn) {
  const auto config = load_config_string(R"(buses:
  - name: arm
    device: [/dev/ttyUSB0
servos: []
)",
                                         "plant.yaml");
  ASSERT_FALSE(config);
  EXPECT_EQ(config.error().file, "plant.yaml");
  // yaml-cpp notices the unclosed `[` at the `:` of the next key, still inside the flow list.
  EXPECT_EQ(config.error().line, 4u);
  EXPECT_EQ(config.error().column, 7u);
  EXPECT_EQ(config.error().message, "YAML syntax error: end of sequence flow not found");
}

TEST(ConfigErrors, BadIndentationIsASyntaxError) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
   device: /dev/ttyUSB0
servos: []
)"),
            "plant.yaml:3:4: YAML syntax error: end of sequence not found");
}

TEST(ConfigErrors, EmptyTextHasNoPlace) {
  EXPECT_EQ(error_text("# nothing here\n"),
            "plant.yaml: the configuration is empty; it needs at least `buses` and `servos` "
            "(examples: config/examples/)");
}

TEST(ConfigErrors, SecondDocumentIsRefused) {
  EXPECT_EQ(error_text(R"(buses: []
---
servos: []
)"),
            "plant.yaml:2:1: a second YAML document starts here; the configuration is one document");
}

TEST(ConfigErrors, TopLevelMustBeAMap) {
  EXPECT_EQ(error_text("- buses\n- servos\n"),
            "plant.yaml:1:1: expected a map of sections (modbus_tcp, buses, servos, sync_groups, logging, mqtt, "
            "state_dir, modbus_rtu_slave, console), got a list");
}

// ---- keys ----

TEST(ConfigErrors, UnknownTopLevelKeySuggestsTheClosest) {
  EXPECT_EQ(error_text(R"(busses: []
servos: []
)"),
            "plant.yaml:1:1: unknown key `busses` at the top level (did you mean `buses`?); allowed keys here: "
            "modbus_tcp, buses, servos, sync_groups, logging, mqtt, state_dir, modbus_rtu_slave, console");
}

TEST(ConfigErrors, UnknownBusKeyListsTheAllowedKeys) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baudrate: 1000000
servos: []
)"),
            "plant.yaml:5:5: unknown key `baudrate` in buses[0] (did you mean `baud`?); allowed keys here: name, "
            "device, protocol, baud, parity, stop_bits, response_timeout_ms, retries, poll_period_ms, "
            "offline_probe_period_ms, reopen_period_ms, poll_fields, poll_range, rs485, rts, rts_delay_us, "
            "byte_timeout_ms, frame_gap, watchdog, on_start, on_stop, stop_deceleration");
}

TEST(ConfigErrors, UnknownServoKeyInAFlowMap) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, mode: fast}
)"),
            "plant.yaml:4:35: unknown key `mode` in servos[0]; allowed keys here: unit, bus, id, table, profile, "
            "byte_order, response_level, read_only, name, safe_stop, stop_deceleration");
}

TEST(ConfigErrors, UnknownKeyInModbusTcpAndLogging) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  port: 502
buses: []
servos: []
)"),
            "plant.yaml:2:3: unknown key `port` in modbus_tcp; allowed keys here: listen, max_connections, "
            "max_waiting, max_waiting_per_address, first_request_timeout_ms, idle_timeout_s, gateway_unit_id, "
            "request_queue_depth, allow, plain, tls");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos: []
logging:
  levle: debug
)"),
            "plant.yaml:5:3: unknown key `levle` in logging (did you mean `level`?); allowed keys here: level, "
            "format, metrics_listen");
}

TEST(ConfigErrors, KeyGivenTwiceNamesBothPlaces) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    baud: 500000
servos: []
)"),
            "plant.yaml:6:5: key `baud` given twice in buses[0] (first at line 5, column 5)");
}

TEST(ConfigErrors, MissingTopLevelSection) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
)"),
            "plant.yaml:1:1: missing required key `servos` at the top level");
}

TEST(ConfigErrors, MissingBusDevicePointsAtTheBus) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    protocol: feetech
    baud: 1000000
servos: []
)"),
            "plant.yaml:2:5: missing required key `device` in buses[0]");
}

TEST(ConfigErrors, MissingServoTable) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1}
)"),
            "plant.yaml:4:5: missing required key `table` in servos[0]");
}

TEST(ConfigErrors, MissingSyncGroupField) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
sync_groups:
  - name: goals
    members: [1]
    holding_register_start: 0
)"),
            "plant.yaml:6:5: missing required key `field` in sync_groups[0]");
}

TEST(ConfigErrors, TimedMoveGroups) {
  const std::string head = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sts}
  - {unit: 3, bus: base, id: 1, table: d55d}
sync_groups:
)";
  EXPECT_EQ(error_text(head + "  - {name: g, field: goal_speed, members: [1, 2], holding_register_start: 0, "
                              "move_time: true}\n"),
            "plant.yaml:9:89: sync_groups[0].move_time: a timed move writes goal positions, but the group writes "
            "`goal_speed`; unit 1 (table sts) has its goal in `goal_position`");
  EXPECT_EQ(error_text(head + "  - {name: g, field: goal_position, members: [1, 2], holding_register_start: 0, "
                              "stretch: true}\n"),
            "plant.yaml:9:90: sync_groups[0].stretch: `stretch` stretches a move time; the group needs "
            "`move_time: true`");
  // The move time register belongs to the block: a group right after it overlaps.
  EXPECT_NE(error_text(head + "  - {name: g, field: goal_position, members: [1, 2], holding_register_start: 0, "
                              "move_time: true}\n"
                              "  - {name: h, field: lock, members: [1, 2], holding_register_start: 2}\n")
                .find("registers 2..3 overlap sync group `g` (0..2"),
            std::string::npos);
}

TEST(ConfigErrors, EmptyValueCountsAsNothingAndPointsAtItsKey) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device:
    protocol: feetech
    baud: 1000000
servos: []
)"),
            "plant.yaml:3:5: buses[0].device: expected a string, got nothing");
}

// ---- types ----

TEST(ConfigErrors, WordWhereAnIntegerBelongs) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: fast
servos: []
)"),
            "plant.yaml:5:11: buses[0].baud: expected an integer (1..4294967295), got `fast`");
}

TEST(ConfigErrors, QuotedNumberIsAString) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: "1000000"
servos: []
)"),
            "plant.yaml:5:11: buses[0].baud: expected an integer (1..4294967295), got the quoted string "
            "\"1000000\"; write numbers without quotes");
}

TEST(ConfigErrors, FractionWhereAnIntegerBelongs) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, response_timeout_ms: 2.5}
servos: []
)"),
            "plant.yaml:2:94: buses[0].response_timeout_ms: expected an integer (1..10000), got `2.5`");
}

TEST(ConfigErrors, MapWhereAListBelongs) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos: {bus: arm}
)"),
            "plant.yaml:3:9: servos: expected a list, got a map");
}

TEST(ConfigErrors, ListWhereAMapBelongs) {
  EXPECT_EQ(error_text(R"(modbus_tcp: [listen]
buses: []
servos: []
)"),
            "plant.yaml:1:13: modbus_tcp: expected a map of keys (listen, max_connections, max_waiting, "
            "max_waiting_per_address, first_request_timeout_ms, idle_timeout_s, "
            "gateway_unit_id, request_queue_depth, allow, plain, tls), got a list");
}

TEST(ConfigErrors, NothingWhereAListBelongsSaysHowToWriteAnEmptyOne) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
)"),
            "plant.yaml:3:1: servos: expected a list, got nothing (write [] for an empty list)");
}

TEST(ConfigErrors, NotABoolean) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, read_only: maybe}
)"),
            "plant.yaml:4:46: servos[0].read_only: expected true or false, got `maybe`");
}

TEST(ConfigErrors, UnknownParityListsTheChoices) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    parity: mark
servos: []
)"),
            "plant.yaml:6:13: buses[0].parity: expected one of none, even, odd, got `mark`");
}

TEST(ConfigErrors, UnknownProtocolListsTheChoices) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: dynamixel
    baud: 1000000
servos: []
)"),
            "plant.yaml:4:15: buses[0].protocol: expected one of feetech, d55d, modbus-rtu, got `dynamixel`");
}

TEST(ConfigErrors, NumberOutsideItsRange) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    retries: 11
servos: []
)"),
            "plant.yaml:6:14: buses[0].retries: 11 is outside 0..10");
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    stop_bits: 3
servos: []
)"),
            "plant.yaml:6:16: buses[0].stop_bits: 3 is outside 1..2");
}

TEST(ConfigErrors, BusNameWithASpace) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: left arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos: []
)"),
            "plant.yaml:2:12: buses[0].name: `left arm` may use letters, digits, '_', '-' and '.' only");
}

TEST(ConfigErrors, ListenWithoutPort) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  listen: 0.0.0.0
buses: []
servos: []
)"),
            "plant.yaml:2:11: modbus_tcp.listen: \"0.0.0.0\" is not HOST:PORT (e.g. 0.0.0.0:502)");
  EXPECT_EQ(error_text(R"(modbus_tcp:
  listen: 0.0.0.0:70000
buses: []
servos: []
)"),
            "plant.yaml:2:11: modbus_tcp.listen: \"0.0.0.0:70000\" has no valid port (0..65535) after the ':'");
}

// ---- buses ----

TEST(ConfigErrors, NoBusAtAll) {
  EXPECT_EQ(error_text(R"(buses: []
servos: []
)"),
            "plant.yaml:1:8: buses: at least one bus is needed");
}

TEST(ConfigErrors, BaudNotInTheFeetechTableListsTheValidRates) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 115201
servos: []
)"),
            "plant.yaml:5:11: buses[0].baud: 115201 bit/s is not a feetech rate; valid rates: 1000000, 500000, "
            "250000, 128000, 115200, 76800, 57600, 38400, 19200, 14400, 9600, 4800");
}

TEST(ConfigErrors, BaudNotInTheD55dTable) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: base, device: /dev/ttyUSB0, protocol: d55d, baud: 1000000}
servos: []
)"),
            "plant.yaml:2:62: buses[0].baud: 1000000 bit/s is not a d55d rate; valid rates: 2400, 9600, 38400, "
            "115200, 256000, 460800, 896000, 921600, 1280000, 1792000");
}

TEST(ConfigErrors, BaudNotInTheModbusRtuTable) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 1000000}
servos: []
)"),
            "plant.yaml:2:68: buses[0].baud: 1000000 bit/s is not a modbus-rtu rate; valid rates: 256000, 128000, "
            "115200, 57600, 56000, 38400, 19200, 14400, 9600, 4800");
}

TEST(ConfigErrors, TwoBusesWithOneName) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: arm, device: /dev/ttyUSB1, protocol: feetech, baud: 1000000}
servos: []
)"),
            "plant.yaml:3:12: buses[1].name: bus name `arm` is already used by buses[0] (line 2, column 12)");
}

TEST(ConfigErrors, TwoBusesOnOneDevice) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB0, protocol: d55d, baud: 115200}
servos: []
)"),
            "plant.yaml:3:26: buses[1].device: /dev/ttyUSB0 is already the device of bus `arm` (line 2, column 25)");
}

TEST(ConfigErrors, ModbusRtuLineKeyOnAFeetechBus) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    rs485: true
servos: []
)"),
            "plant.yaml:6:5: buses[0]: `rs485` applies to modbus-rtu buses only; bus `arm` is feetech");
}

TEST(ConfigErrors, RtsDelayWithoutRts) {
  EXPECT_EQ(error_text(R"(buses:
  - name: lift
    device: /dev/ttyUSB0
    protocol: modbus-rtu
    baud: 115200
    rts_delay_us: 100
servos: []
)"),
            "plant.yaml:6:5: buses[0]: `rts_delay_us` needs `rts: up` or `rts: down`");
}

TEST(ConfigErrors, PollFieldsAndPollRangeTogether) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    poll_fields: [present_position]
    poll_range: {start: 56, count: 15}
servos: []
)"),
            "plant.yaml:7:5: buses[0]: give either poll_fields or poll_range, not both");
}

TEST(ConfigErrors, PollFieldListedTwice) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    poll_fields: [present_position, moving, present_position]
servos: []
)"),
            "plant.yaml:6:45: buses[0].poll_fields[2]: field `present_position` is listed twice");
}

TEST(ConfigErrors, PollFieldMissingFromOneTableOnTheBus) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    poll_fields: [present_position, status]
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sms1}
)"),
            "plant.yaml:6:37: buses[0].poll_fields[1]: servos[1] (unit 2, table sms1) has no field `status`; its "
            "fields: software_version, id, baud_rate, return_delay, response_level, min_angle_limit, "
            "max_angle_limit, max_temperature, max_input_voltage, min_input_voltage, max_torque, pwm_phase_mode, "
            "unload_conditions, led_alarm_conditions, p_gain, d_gain, i_gain, min_pwm, cw_insensitive_zone, "
            "ccw_insensitive_zone, integral_limit, differential_sampling_factor, torque_step, position_step, "
            "position_correction, operating_mode, protection_current, torque_switch, acceleration, goal_position, "
            "run_time, "
            "run_speed, lock, present_position, present_speed, present_load, present_voltage, "
            "present_temperature, reg_write_flag, error, moving, present_goal_position, present_current");
}

TEST(ConfigErrors, PollRangePastTheEndOfATable) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    poll_range: {start: 56, count: 20}
servos:
  - {bus: arm, id: 1, table: sts}
)"),
            "plant.yaml:6:36: buses[0].poll_range: 56..75 runs past the end of servos[0] (unit 1, table sts), "
            "whose last address is 70");
}

TEST(ConfigErrors, PollRangeOverTheModbusReadLimit) {
  EXPECT_EQ(error_text(R"(buses:
  - name: lift
    device: /dev/ttyUSB0
    protocol: modbus-rtu
    baud: 115200
    poll_range: {start: 0x100, count: 126}
servos:
  - {bus: lift, id: 1, table: smsmb}
)"),
            "plant.yaml:6:39: buses[0].poll_range.count: one read takes at most 125 registers on a modbus-rtu bus");
}

// ---- servos ----

TEST(ConfigErrors, UnknownBusNameListsTheBuses) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {bus: arms, id: 1, table: sts}
)"),
            "plant.yaml:5:11: servos[0].bus: unknown bus `arms`; configured buses: arm, base");
}

TEST(ConfigErrors, DuplicateUnitIdNamesBothPlaces) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 7, bus: arm, id: 1, table: sts}
  - {unit: 7, bus: arm, id: 2, table: sts}
)"),
            "plant.yaml:5:12: servos[1]: unit 7 is already used by servos[0] (line 4, column 12)");
}

TEST(ConfigErrors, DuplicateUnitFromADefaultedUnitSaysSo) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {unit: 3, bus: arm, id: 1, table: sts}
  - {bus: base, id: 3, table: d55d}
)"),
            "plant.yaml:6:21: servos[1]: unit 3 is already used by servos[0] (line 5, column 12); the unit "
            "defaults to the servo id, give `unit`");
}

TEST(ConfigErrors, SameServoIdTwiceOnOneBus) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 1, bus: arm, id: 5, table: sts}
  - {unit: 2, bus: arm, id: 5, table: sts}
)"),
            "plant.yaml:5:29: servos[1]: servo id 5 is already on bus `arm` as servos[0] (unit 1, line 4, column 29); "
            "IDs on one bus must differ, or a second unit of the same servo must be `read_only: true` (two writable "
            "units would let two clients command one servo against each other)");
}

TEST(ConfigErrors, SecondUnitOfAServoMustBeReadOnlyAndDescribeTheSameServo) {
  const std::string head = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 1, bus: arm, id: 5, table: sts}
  - {unit: 2, bus: arm, id: 5, table: sts, read_only: true}
)";
  // A third unit that writes: the servo already has its writable unit 1.
  EXPECT_EQ(error_text(head + "  - {unit: 3, bus: arm, id: 5, table: sts}\n"),
            "plant.yaml:6:29: servos[2]: servo id 5 is already on bus `arm` as servos[0] (unit 1, line 4, column 29); "
            "IDs on one bus must differ, or a second unit of the same servo must be `read_only: true` (two writable "
            "units would let two clients command one servo against each other)");
  EXPECT_EQ(error_text(head + "  - {unit: 3, bus: arm, id: 5, table: sms1, read_only: true}\n"),
            "plant.yaml:6:29: servos[2]: servo id 5 is already on bus `arm` as servos[0] (unit 1, line 4, column 29) "
            "with table sts, this one is table sms1; IDs on one bus must differ, or a second unit of the same servo "
            "must have its table");
  EXPECT_EQ(error_text(head + "  - {unit: 3, bus: arm, id: 5, table: sts, read_only: true, safe_stop: torque_off}\n"),
            "plant.yaml:6:5: servos[2]: servo id 5 is already on bus `arm` as servos[0] (unit 1, line 4, column 29) "
            "with another safe_stop; units of one servo must agree on byte_order, response_level, safe_stop and "
            "stop_deceleration (they "
            "describe the servo): give both the same");
  EXPECT_EQ(error_text(head + "  - {unit: 3, bus: arm, id: 5, table: sts, read_only: true, byte_order: high-first}\n"),
            "plant.yaml:6:5: servos[2]: servo id 5 is already on bus `arm` as servos[0] (unit 1, line 4, column 29) "
            "with another byte_order; units of one servo must agree on byte_order, response_level, safe_stop and "
            "stop_deceleration (they "
            "describe the servo): give both the same");
  // A read-only view cannot be a sync group member (a group writes).
  EXPECT_NE(error_text(head + "sync_groups:\n  - {name: g, field: goal_position, members: [1, 2], "
                              "holding_register_start: 0}\n")
                .find("unit 2 is read_only"),
            std::string::npos);
}

TEST(ConfigErrors, TwoServosWithOneName) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, name: elbow}
  - {bus: arm, id: 2, table: sts, name: elbow}
)"),
            "plant.yaml:5:5: servos[1]: name `elbow` is already used by servos[0] (line 4, column 5)");
}

TEST(ConfigErrors, UnitClashesWithTheGatewayUnit) {
  EXPECT_EQ(error_text(R"(modbus_tcp:
  gateway_unit_id: 1
buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
)"),
            "plant.yaml:6:20: servos[0]: unit 1 is the gateway's own unit (modbus_tcp.gateway_unit_id, line 2, "
            "column 20); the unit defaults to the servo id, give `unit`");
  EXPECT_EQ(error_text(R"(modbus_tcp:
  gateway_unit_id: 200
buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 200, bus: arm, id: 1, table: sts}
)"),
            "plant.yaml:6:12: servos[0]: unit 200 is the gateway's own unit (modbus_tcp.gateway_unit_id, line 2, "
            "column 20)");
}

TEST(ConfigErrors, UnitOutsideModbusSlaveRange) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 248, bus: arm, id: 1, table: sts}
)"),
            "plant.yaml:4:12: servos[0].unit: 248 is outside 1..247");
}

TEST(ConfigErrors, BroadcastIdIsNoServoId) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {unit: 1, bus: arm, id: 254, table: sts}
)"),
            "plant.yaml:4:29: servos[0].id: 254 is outside 0..253");
}

TEST(ConfigErrors, ModbusSlaveIdZeroIsBroadcast) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {unit: 1, bus: lift, id: 0, table: smsmb}
)"),
            "plant.yaml:4:30: servos[0].id: 0 is outside 1..247");
}

TEST(ConfigErrors, ServoIdZeroNeedsAUnit) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 0, table: sts}
)"),
            "plant.yaml:4:20: servos[0].id: servo id 0 cannot be its unit id (units are 1..247); give `unit`");
}

TEST(ConfigErrors, UnknownTableListsTheTables) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts3215}
)"),
            "plant.yaml:4:30: servos[0].table: unknown table `sts3215`; allowed: sts, sms1, d55d, smsmb, scs, "
            "passthrough");
}

TEST(ConfigErrors, PacketTableOnTheWrongBus) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: base, device: /dev/ttyUSB0, protocol: d55d, baud: 115200}
servos:
  - {bus: base, id: 1, table: sts}
)"),
            "plant.yaml:4:31: servos[0].table: table sts is spoken on feetech buses; bus `base` is d55d");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: d55d}
)"),
            "plant.yaml:4:30: servos[0].table: table d55d is spoken on d55d buses; bus `arm` is feetech");
}

TEST(ConfigErrors, SmsmbTableNeedsAModbusRtuBus) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: smsmb}
)"),
            "plant.yaml:4:30: servos[0].table: table smsmb is spoken on modbus-rtu buses; bus `arm` is feetech");
}

TEST(ConfigErrors, ModbusBusTakesNoPacketTable) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: lift, id: 1, table: sms1}
)"),
            "plant.yaml:4:31: servos[0].table: table sms1 is spoken on feetech buses; bus `lift` is modbus-rtu");
}

TEST(ConfigErrors, PassthroughNeedsAModbusRtuBus) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: passthrough}
)"),
            "plant.yaml:4:30: servos[0].table: passthrough forwards Modbus PDUs and needs a modbus-rtu bus; bus "
            "`arm` is feetech");
}

TEST(ConfigErrors, Sms1CannotRunAtTheStsOnlyRates) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 19200}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sms1}
)"),
            "plant.yaml:5:30: servos[1].table: sms1 servos cannot run at 19200 bit/s (bus `arm`): their baud table "
            "ends at code 7 (38400 bit/s)");
}

TEST(ConfigErrors, ScsServosStopAtBaudCode7AndHaveNoSmsmbProfile) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: head, device: /dev/ttyUSB0, protocol: feetech, baud: 19200}
servos:
  - {bus: head, id: 1, table: scs}
)"),
            "plant.yaml:4:31: servos[0].table: scs servos cannot run at 19200 bit/s (bus `head`): their baud table "
            "ends at code 7 (38400 bit/s)");
  EXPECT_EQ(error_text(R"(buses:
  - {name: head, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: head, id: 1, table: scs, profile: smsmb}
)"),
            "plant.yaml:4:45: servos[0].profile: profile smsmb shows sts and sms1 servos as SMSMB servos; this "
            "servo's table is scs");
}

TEST(ConfigErrors, SmsmbProfileOnAD55dServo) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: base, device: /dev/ttyUSB0, protocol: d55d, baud: 115200}
servos:
  - {bus: base, id: 1, table: d55d, profile: smsmb}
)"),
            "plant.yaml:4:46: servos[0].profile: profile smsmb shows sts and sms1 servos as SMSMB servos; this "
            "servo's table is d55d");
}

TEST(ConfigErrors, ProfileOnAPassthroughUnit) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: lift, id: 1, table: passthrough, profile: native}
)"),
            "plant.yaml:4:53: servos[0].profile: passthrough units have no profile; remove the key");
}

TEST(ConfigErrors, UnknownProfile) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, profile: plc}
)"),
            "plant.yaml:4:44: servos[0].profile: expected one of native, smsmb, got `plc`");
}

TEST(ConfigErrors, ByteOrderOnARegisterTable) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: lift, id: 1, table: smsmb, byte_order: low-first}
)"),
            "plant.yaml:4:50: servos[0].byte_order: byte_order applies to the packet tables (sts, sms1, d55d); "
            "smsmb registers are always high byte first");
}

TEST(ConfigErrors, UnknownByteOrder) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, byte_order: little}
)"),
            "plant.yaml:4:47: servos[0].byte_order: expected one of low-first, high-first, got `little`");
}

TEST(ConfigErrors, ResponseLevelOutsideTheTablesRange) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, response_level: 2}
)"),
            "plant.yaml:4:51: servos[0].response_level: 2 is outside 0..1");
}

TEST(ConfigErrors, ResponseLevelOnAModbusServo) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: lift, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: lift, id: 1, table: smsmb, response_level: 1}
)"),
            "plant.yaml:4:54: servos[0].response_level: smsmb servos have no response level (a Modbus slave "
            "answers every unicast request)");
}

// ---- sync groups ----

constexpr std::string_view kArmAndBase = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
  - {name: lift, device: /dev/ttyUSB2, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sms1}
  - {bus: arm, id: 3, table: sts, read_only: true}
  - {bus: base, id: 11, table: d55d}
  - {bus: lift, id: 21, table: passthrough}
sync_groups:
)";  // lines 1..11; the group under test is line 12

std::string with_groups(std::string_view groups) { return std::string(kArmAndBase) + std::string(groups); }

TEST(ConfigErrors, SyncGroupMemberIsNoUnit) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: arm, field: goal_position, members: [1, 2, 9], holding_register_start: 0}\n")),
      "plant.yaml:12:55: sync_groups[0].members[2]: unknown unit 9; configured units: 1, 2, 3, 11, 21");
}

TEST(ConfigErrors, SyncGroupMemberIsAPassthroughUnit) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: arm, field: goal_position, members: [1, 21], holding_register_start: 0}\n")),
      "plant.yaml:12:52: sync_groups[0].members[1]: unit 21 is a passthrough unit and has no fields to write");
}

TEST(ConfigErrors, SyncGroupMemberIsReadOnly) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: arm, field: goal_position, members: [1, 3], holding_register_start: 0}\n")),
      "plant.yaml:12:52: sync_groups[0].members[1]: unit 3 is read_only");
}

TEST(ConfigErrors, SyncGroupMemberListedTwice) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: arm, field: goal_position, members: [1, 2, 1], holding_register_start: 0}\n")),
      "plant.yaml:12:55: sync_groups[0].members[2]: unit 1 is listed twice");
}

TEST(ConfigErrors, SyncGroupWithoutMembers) {
  EXPECT_EQ(error_text(with_groups("  - {name: arm, field: goal_position, members: [], holding_register_start: 0}\n")),
            "plant.yaml:12:48: sync_groups[0].members: a sync group needs at least one member unit");
}

TEST(ConfigErrors, SyncGroupFieldMissingFromAMembersTable) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: speeds, field: goal_speed, members: [1, 11], holding_register_start: 0}\n")),
      "plant.yaml:12:27: sync_groups[0].field: unit 11 (table d55d) has no field `goal_speed`; its fields: "
      "vendor_code, software_version, id, baud_rate, return_delay, cw_angle_limit, ccw_angle_limit, "
      "max_temperature, max_current, angle_resolution, response_level, heartbeat_enable, unload_conditions, "
      "photo_switch_zero_direction, rs485_termination, base_acceleration, base_deceleration, "
      "photo_switch_homing, clear_unload_condition, goal_position, run_speed, acceleration, deceleration, "
      "present_position, present_speed, accumulated_angle, moving, brake, reg_write_flag, "
      "present_temperature, sleep, photo_switch_state, move_without_photo_coupler");
}

TEST(ConfigErrors, SyncGroupFieldIsReadOnly) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: arm, field: present_position, members: [1], holding_register_start: 0}\n")),
      "plant.yaml:12:24: sync_groups[0].field: `present_position` is read-only in table sts (unit 1); a sync "
      "group writes its field");
}

TEST(ConfigErrors, SyncGroupFieldAtTwoAddressesOnOneBus) {
  // `lock` is byte 55 in sts and byte 48 in sms1: one SYNC WRITE frame cannot carry both.
  EXPECT_EQ(error_text(with_groups("  - {name: locks, field: lock, members: [1, 2], holding_register_start: 0}\n")),
            "plant.yaml:12:26: sync_groups[0].field: `lock` is at address 48 (size 1) on unit 2 but at address 55 "
            "(size 1) on unit 1; members on one bus (`arm`) share one SYNC WRITE frame, so the field must be at "
            "one address");
}

TEST(ConfigErrors, SyncGroupBlocksOverlap) {
  EXPECT_EQ(error_text(with_groups(R"(  - {name: a, field: goal_position, members: [1, 2], holding_register_start: 10}
  - {name: b, field: goal_position, members: [11, 1], holding_register_start: 11}
)")),
            "plant.yaml:13:79: sync_groups[1].holding_register_start: registers 11..12 overlap sync group `a` "
            "(10..11, line 12, column 78)");
}

TEST(ConfigErrors, SyncGroupNamedTwice) {
  EXPECT_EQ(error_text(with_groups(R"(  - {name: a, field: goal_position, members: [1], holding_register_start: 0}
  - {name: a, field: goal_position, members: [2], holding_register_start: 1}
)")),
            "plant.yaml:13:12: sync_groups[1].name: sync group `a` is already defined as sync_groups[0]");
}

TEST(ConfigErrors, SyncGroupBlockPastTheLastRegister) {
  EXPECT_EQ(
      error_text(with_groups("  - {name: a, field: goal_position, members: [1, 2], holding_register_start: 65535}\n")),
      "plant.yaml:12:78: sync_groups[0].holding_register_start: 65535 is outside 0..65534");
}

// ---- files ----

TEST(ConfigErrors, MissingFileNamesThePath) {
  const auto config = load_config_file("/nonexistent/sms-gateway.yaml");
  ASSERT_FALSE(config);
  EXPECT_EQ(config.error().line, 0u);
  EXPECT_EQ(config.error().to_string(), "/nonexistent/sms-gateway.yaml: cannot open: No such file or directory");
}

TEST(ConfigErrors, DirectoryIsNoFile) {
  const auto config = load_config_file("/tmp");
  ASSERT_FALSE(config);
  EXPECT_EQ(config.error().to_string(), "/tmp: is a directory; give the configuration file");
}

}  // namespace
}  // namespace sms::config

namespace sms::config {
namespace {

// Fuzz finding (tests/fuzz/corpus/fuzz_config/finding-lone-comma-endless-loadall.yaml): yaml-cpp 0.7's
// LoadAll produced empty documents forever for a lone comma; the loader must answer at once.
TEST(ConfigErrors, LoneCommaIsRefusedInsteadOfLoopingForever) {
  EXPECT_EQ(error_text(","), "plant.yaml:1:1: a second YAML document starts here; the configuration is one document");
}

// Fuzz findings (finding-servo-name-*.yaml): such names did not survive a dump and would garble logs.
TEST(ConfigErrors, NameWithControlCharacterOrBrokenUtf8IsRefused) {
  const std::string prefix =
      "buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}\n"
      "servos:\n  - {bus: arm, id: 1, table: sts, name: \"a";
  EXPECT_EQ(error_text(prefix + "\\x01b\"}\n"),
            "plant.yaml:4:41: servos[0].name: must be printable UTF-8 text (it has a control character or bytes "
            "that are not UTF-8); names end up in logs and metrics labels");
  EXPECT_EQ(error_text(prefix + "\xFF" + "b\"}\n"),
            "plant.yaml:4:41: servos[0].name: must be printable UTF-8 text (it has a control character or bytes "
            "that are not UTF-8); names end up in logs and metrics labels");
  EXPECT_TRUE(load_config_string(prefix + "\xC3\xA9t\xC3\xA9\"}\n", "plant.yaml").has_value())
      << "UTF-8 names are fine";
}

}  // namespace
}  // namespace sms::config

// ---- safety (docs/PLC_GUIDE.md "Safety") ----

namespace sms::config {
namespace {

TEST(ConfigErrors, WatchdogTimeoutOutOfRangeNamesTheValue) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, watchdog: {timeout_ms: 5}}
servos: []
)"),
            "plant.yaml:2:96: buses[0].watchdog.timeout_ms: 5 is outside 10..600000");
}

TEST(ConfigErrors, WatchdogNeedsATimeoutAndKnownKeysAndValues) {
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    watchdog: {feed: any_write}
servos: []
)"),
            "plant.yaml:6:15: missing required key `timeout_ms` in buses[0].watchdog");
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    watchdog: {timeout_ms: 200, feed: heartbeat}
servos: []
)"),
            "plant.yaml:6:39: buses[0].watchdog.feed: expected one of any_write, heartbeat_register, got `heartbeat`");
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    watchdog: {timeout_ms: 200, timout: 3}
servos: []
)"),
            "plant.yaml:6:33: unknown key `timout` in buses[0].watchdog; allowed keys here: timeout_ms, feed, action");
  EXPECT_EQ(error_text(R"(buses:
  - name: arm
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
    watchdog: {timeout_ms: 200, action: brake}
servos: []
)"),
            "plant.yaml:6:41: buses[0].watchdog.action: expected one of hold, torque_off, none, got `brake`");
}

TEST(ConfigErrors, StartStopAndSafeStopActionsAreChecked) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, on_stop: park}
servos: []
)"),
            "plant.yaml:2:82: buses[0].on_stop: expected one of hold, torque_off, none, got `park`");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, on_start: none}
servos: []
)"),
            "plant.yaml:2:83: buses[0].on_start: expected one of keep, hold, torque_off, got `none`");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, safe_stop: freeze}
)"),
            "plant.yaml:4:46: servos[0].safe_stop: expected one of hold, torque_off, none, got `freeze`");
  EXPECT_EQ(error_text(R"(buses:
  - {name: io, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200}
servos:
  - {bus: io, id: 1, table: passthrough, safe_stop: hold}
)"),
            "plant.yaml:4:42: servos[0].safe_stop: a passthrough unit has no table the gateway could stop it with; "
            "remove the key");
}

TEST(ConfigErrors, AStopDecelerationMustFitEveryServoItApplies) {
  // scs has no ramp to set.
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: scs, stop_deceleration: 20}
)"),
            "plant.yaml:4:54: servos[0].stop_deceleration: table scs has no acceleration field: its servos change "
            "speed at once, and a stop ramp cannot be set");
  // A bus's value is checked against each servo that takes it, at that servo.
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, stop_deceleration: 20}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: scs}
)"),
            "plant.yaml:5:20: servos[1]: bus `arm`'s stop_deceleration 20 does not fit this servo: table scs has no "
            "acceleration field: its servos change speed at once, and a stop ramp cannot be set; give the servo its "
            "own stop_deceleration, or remove the bus's");
  EXPECT_NE(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, stop_deceleration: 255}
)")
                .find("takes 1..254 (acceleration, 100 steps/s²), not 255"),
            std::string::npos);
  EXPECT_NE(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts, stop_deceleration: 0}
)")
                .find("stop_deceleration"),
            std::string::npos);
}

TEST(ConfigErrors, SyncGroupsMustLeaveTheHeartbeatRegistersFree) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
sync_groups:
  - {name: goals, field: goal_position, members: [1], holding_register_start: 1000}
)"),
            "plant.yaml:6:79: sync_groups[0].holding_register_start: registers 1000..1000 overlap the buses' "
            "watchdog heartbeat registers 1000..1000 (1000 + bus index); move the group");
}

TEST(ConfigLoadSafety, WatchdogAndActionsLoadWithTheirDefaults) {
  const auto config = load_config_string(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000,
     watchdog: {timeout_ms: 200, feed: heartbeat_register, action: torque_off}, on_start: hold, on_stop: none}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200}
servos:
  - {bus: arm, id: 1, table: sts, safe_stop: torque_off}
  - {bus: arm, id: 2, table: sts}
)",
                                         "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  const BusConfig& arm = config->buses[0];
  ASSERT_TRUE(arm.watchdog);
  EXPECT_EQ(arm.watchdog->timeout, std::chrono::milliseconds{200});
  EXPECT_EQ(arm.watchdog->feed, WatchdogFeed::HeartbeatRegister);
  EXPECT_EQ(arm.watchdog->action, modbus_map::StopAction::TorqueOff);
  EXPECT_EQ(arm.on_start, StartAction::Hold);
  EXPECT_EQ(arm.on_stop, modbus_map::StopAction::None);
  const BusConfig& base = config->buses[1];
  EXPECT_FALSE(base.watchdog);
  EXPECT_EQ(base.on_start, StartAction::Keep);
  EXPECT_EQ(base.on_stop, modbus_map::StopAction::Hold);
  EXPECT_EQ(effective_safe_stop(config->servos[0]), modbus_map::StopAction::TorqueOff);
  EXPECT_EQ(effective_safe_stop(config->servos[1]), modbus_map::StopAction::Hold);
  // Dumped and loaded back: the same configuration.
  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string();
  EXPECT_EQ(*again, *config);
}

}  // namespace
}  // namespace sms::config

namespace sms::config {
namespace {

TEST(ConfigErrors, FrameGapNamesTheValidForms) {
  EXPECT_EQ(error_text(R"(buses:
  - {name: line, device: /dev/ttyUSB0, protocol: modbus-rtu, baud: 115200, frame_gap: 2ms}
servos: []
)"),
            "plant.yaml:2:87: buses[0].frame_gap: \"2ms\" is not a frame gap; write spec (3.5 characters, 1.75 ms "
            "above 19200 bit/s), 3.5chars (3.5 characters at every rate) or a time such as 500us (0us..1000000us)");
  EXPECT_EQ(error_text(R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000, frame_gap: spec}
servos: []
)"),
            "plant.yaml:2:73: buses[0]: `frame_gap` applies to modbus-rtu buses only; bus `arm` is feetech");
}

}  // namespace
}  // namespace sms::config
