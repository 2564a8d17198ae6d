#pragma once
// `sms-gateway scan`: which servos answer on a line, at which rate, with which ID.
//
// For each rate (every rate of the protocol's baud table, or the ones asked for) and each ID
// (0-253 on packet buses, 1-247 on modbus-rtu, or the ones asked for): one PING (modbus-rtu:
// FC03 of register 0) with a timeout sized from the rate (tool_link.h). Packet protocols first
// send a broadcast PING, which every servo answers: a rate where nothing at all comes back is
// skipped after one timeout instead of 254.
//
// For each servo found: its identity (model, firmware) and a check for a second servo on the
// same ID. Two servos on one ID answer a PING with identical frames (a PING carries no data),
// so the check reads present_position three times: two servos never sit at exactly the same
// position, their answers overlap on the wire and arrive damaged. A late answer overlapping
// the next request looks the same, so a suspicion is confirmed with reads that wait 20 ms
// longer; only when most of those come back damaged too (or a PING is answered only with
// garbage even then) is the ID reported as a conflict.
#include <chrono>
#include <cstdint>
#include <string>
#include <vector>

#include "gateway/bus/poll_cache.h"
#include "gateway/tools/tool_link.h"
#include "gateway/tools/tool_servo.h"
#include "modbus_map/control_table.h"
#include "protocol/expected.h"

namespace sms::gateway {

struct ScanOptions {
  std::vector<std::uint32_t> bauds;  // empty: the protocol's whole baud table (docs/PROTOCOL.md §3)
  std::vector<std::uint8_t> ids;     // empty: every unicast ID of the protocol
  modbus_map::TableId table = modbus_map::TableId::Sts;  // how to read identity and position
  bool broadcast_probe = true;  // packet protocols: skip rates where a broadcast PING stays unanswered
};

struct ScanFinding {
  std::uint32_t baud = 0;
  std::uint8_t id = 0;
  // The table the servo speaks: the scan's, or scs / sts as the servo's byte-order flag
  // (address 2) says when scanning a feetech bus.
  modbus_map::TableId table = modbus_map::TableId::Sts;
  ServoIdentity identity;
  std::uint8_t status = 0;  // ERROR byte of the PING answer; modbus-rtu: exception code (not an SMSMB servo)
  bool conflict = false;    // two or more servos answer on this ID
  std::string note;
};

struct ScanReport {
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  modbus_map::TableId table = modbus_map::TableId::Sts;
  std::vector<std::uint32_t> bauds;          // tried, in order
  std::vector<std::uint32_t> skipped_bauds;  // nothing answered the broadcast PING there
  std::size_t ids_per_baud = 0;
  std::vector<ScanFinding> found;
  std::chrono::milliseconds elapsed{0};
};

// The link must be open; it is left at the last rate tried. Errors: a rate outside the table,
// an ID outside the protocol's range, the port failing.
Expected<ScanReport> scan_bus(ServoLink& link, const ScanOptions& options, const Say& say);

// One line per servo (baud, id, model, firmware, note) and a summary line.
std::string format_scan(const ScanReport& report);

// A configuration for sms-gateway (config/README.md) with the servos found on `device`: one
// bus at the rate where most servos answer; servos found at other rates, and conflicting IDs,
// are listed as comments saying what to do. Units are the servo IDs where they can be.
std::string scan_config_yaml(const ScanReport& report, const LinkSettings& link);

}  // namespace sms::gateway
