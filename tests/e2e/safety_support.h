#pragma once
// What the safety end-to-end tests share (docs/PLC_GUIDE.md "Safety"): one servo of each protocol and a
// table of each (feetech sts and sms1, d55d, modbus-rtu smsmb), the writes that set it turning,
// a motion write, a harmless write, and the gateway unit's safety registers.
#include <gtest/gtest.h>

#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

inline constexpr int kUnit = 1;
inline constexpr int kGateway = 255;
// Longer than the worst transaction of a 115 200 bit/s bus (--check-config refuses shorter).
inline constexpr int kWatchdogTimeoutMs = 500;
// Gateway unit registers (docs/PLC_GUIDE.md "Safety"): bus 0's block starts at 100.
inline constexpr int kEStopLatchedRegister = 10;
inline constexpr int kOwedStops = 13;    // servos owed a safe stop, every bus
inline constexpr int kFailedStops = 14;  // 14-15: safe stops that failed (32-bit)
inline constexpr int kBus0WatchdogState = 110;
inline constexpr int kBus0Trips = 112;
inline constexpr int kBus0LastCause = 115;
inline constexpr int kBus0OwedStops = 119;
inline constexpr int kEStopCoil = 1;
inline constexpr int kWatchdogCoil = 2;
inline constexpr int kOwedStopInput = 3;  // discrete input: a stop is owed somewhere
inline constexpr int kHeartbeatRegister = 1000;
inline constexpr std::uint16_t kTripped = 3;
inline constexpr std::uint16_t kRunning = 2;

struct Write {
  int address;
  std::uint16_t value;
};

struct Protocol {
  std::string name;          // test name suffix
  std::string sim_servo;     // sms-sim --servo
  std::string bus_protocol;  // config
  int baud;
  std::string table;
  std::vector<Write> spin;          // puts servo 1 into speed mode and turns it
  Write goal;                       // a goal position write (a motion write)
  Write harmless;                   // a write that cannot move anything (allowed while latched)
  std::optional<Write> torque_off;  // allowed while latched
  std::string torque_field;         // sim field name, empty when the table has none
  int goal_address;
  int present_address;
};

inline void PrintTo(const Protocol& protocol, std::ostream* out) { *out << protocol.name; }

inline std::string config_for(const Protocol& p, const std::string& pty, const std::string& bus_extra) {
  return "buses:\n  - {name: line, device: \"" + pty + "\", protocol: " + p.bus_protocol +
         ", baud: " + std::to_string(p.baud) + bus_extra + "}\nservos:\n  - {bus: line, id: 1, table: " + p.table +
         "}\n";
}

inline std::string watchdog(const std::string& feed, int timeout_ms = kWatchdogTimeoutMs) {
  return ", watchdog: {timeout_ms: " + std::to_string(timeout_ms) + ", feed: " + feed + "}";
}

// Every protocol, a table of each.
inline const std::vector<Protocol> kSafetyProtocols{
    Protocol{"feetech_sts",
             "1:sts",
             "feetech",
             1000000,
             "sts",
             {{33, 1}, {46, 1500}},
             {42, 3000},
             {41, 20},
             Write{40, 0},
             "torque_enable",
             42,
             56},
    Protocol{"feetech_sms1",
             "1:sms1",
             "feetech",
             1000000,
             "sms1",
             {{35, 1}, {40, 1}, {46, 1500}},
             {42, 3000},
             {48, 1},
             Write{40, 0},
             "torque_switch",
             42,
             56},
    Protocol{"d55d",
             "1:d55d:d55d:115200",
             "d55d",
             115200,
             "d55d",
             {{6, 0}, {8, 0}, {32, 300}},
             {30, 90},
             {34, 20},
             std::nullopt,
             "",
             30,
             36},
    Protocol{"modbus_rtu_smsmb",
             "1:smsmb:modbus-rtu:115200",
             "modbus-rtu",
             115200,
             "smsmb",
             {{0x10, 1}, {0x81, 1}, {0x83, 500}},
             {0x80, 3000},
             {0x82, 20},
             Write{0x81, 0},
             "torque_switch",
             0x80,
             0x101},
};
inline std::string protocol_name(const testing::TestParamInfo<Protocol>& info) { return info.param.name; }

}  // namespace sms::e2e
