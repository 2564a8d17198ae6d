#pragma once
// The one place that picks Modbus exception codes (docs/PLC_GUIDE.md "Exceptions"). Everything
// else in the gateway names what went wrong as a Fault; exception_code() turns it into the
// code a client sees. The mapping is a table, so the contract can be read off it.
#include <cstdint>
#include <span>
#include <string_view>

#include "modbus_map/register_map.h"

namespace sms::gateway {

enum class Fault : std::uint8_t {
  UnsupportedFunction,  // function code the gateway does not serve
  BadAddress,           // beyond the table, read-only field, only non-field addresses
  QuantityOverLimit,    // count 0 or over the Modbus limits, or past address 65535
  BadValue,             // outside the field's range
  MalformedRequest,     // PDU length / byte count inconsistent with its function
  ServoRefused,         // the servo's ERROR byte says instruction or checksum error
  ServoCorrupt,         // replies stayed corrupt through every retry
  QueueFull,            // the bus's bounded request queue is full
  UnknownUnit,          // no unit with that id
  BusDown,              // the unit's bus port is missing or closed
  GatewayStopping,      // the gateway is shutting down; the bus no longer takes work
  ServoTimeout,         // the servo did not answer after the configured retries
  MotionBlocked,        // the safety rules refuse a motion write (e-stop latched, watchdog tripped)
  InternalError,        // the gateway failed inside (a defect); the request did nothing
};

struct FaultSpec {
  Fault fault;
  std::uint8_t exception_code;
  std::string_view meaning;  // for logs and docs
};

// Every Fault with its exception code, in enum order.
std::span<const FaultSpec> fault_table();

std::uint8_t exception_code(Fault fault);
std::string_view to_string(Fault fault);

// The Fault a register-map refusal stands for (modbus_map decides 0x02 / 0x03 / 0x04 there).
Fault fault_from(modbus_map::ModbusException code);

}  // namespace sms::gateway
