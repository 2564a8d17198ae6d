#pragma once
// Modbus function codes, quantity limits, exception names (Modbus application protocol v1.1b3
// §6, §7) and the request PDUs the gateway sends as a master: the one home of these, shared by
// the register map, the TCP side, the RTU transactor and the tools. Header only.
#include <array>
#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

namespace sms::protocol::function_code {

inline constexpr std::uint8_t kReadCoils = 0x01;
inline constexpr std::uint8_t kReadDiscreteInputs = 0x02;
inline constexpr std::uint8_t kReadHoldingRegisters = 0x03;
inline constexpr std::uint8_t kReadInputRegisters = 0x04;
inline constexpr std::uint8_t kWriteSingleCoil = 0x05;
inline constexpr std::uint8_t kWriteSingleRegister = 0x06;
inline constexpr std::uint8_t kWriteMultipleCoils = 0x0F;
inline constexpr std::uint8_t kWriteMultipleRegisters = 0x10;
inline constexpr std::uint8_t kReportServerId = 0x11;  // SMSMB servos answer it (docs/PROTOCOL.md §1.3)
inline constexpr std::uint8_t kReadWriteMultipleRegisters = 0x17;
// An exception answer carries the request's function code with this bit set.
inline constexpr std::uint8_t kExceptionBit = 0x80;

}  // namespace sms::protocol::function_code

namespace sms::protocol::modbus_limits {

inline constexpr std::uint16_t kReadBits = 2000;
inline constexpr std::uint16_t kReadRegisters = 125;
inline constexpr std::uint16_t kWriteBits = 1968;
inline constexpr std::uint16_t kWriteRegisters = 123;
inline constexpr std::uint16_t kReadWriteRead = 125;   // FC23's read half
inline constexpr std::uint16_t kReadWriteWrite = 121;  // FC23's write half

}  // namespace sms::protocol::modbus_limits

namespace sms::protocol {

// What a Modbus function does to the unit it is sent to, so that a read-only unit (or a role
// without write rights) can refuse everything that may change it.
enum class FunctionEffect : std::uint8_t {
  Reads,    // only reads
  Writes,   // writes (FC23 writes and reads: it writes)
  Unknown,  // diagnostics, vendor functions, codes the gateway does not know: may change state
};

struct ModbusFunction {
  std::uint8_t code;
  std::string_view name;  // Modbus Application Protocol v1.1b3 name, snake_case (metrics labels)
  FunctionEffect effect;
  bool served;  // the gateway serves it for table units (docs/PLC_GUIDE.md "A servo unit")
};

// The public function codes (Modbus Application Protocol v1.1b3 §5.1), ascending by code.
inline constexpr std::array<ModbusFunction, 19> kModbusFunctions{{
    {0x01, "read_coils", FunctionEffect::Reads, true},
    {0x02, "read_discrete_inputs", FunctionEffect::Reads, true},
    {0x03, "read_holding_registers", FunctionEffect::Reads, true},
    {0x04, "read_input_registers", FunctionEffect::Reads, true},
    {0x05, "write_single_coil", FunctionEffect::Writes, true},
    {0x06, "write_single_register", FunctionEffect::Writes, true},
    {0x07, "read_exception_status", FunctionEffect::Reads, false},
    {0x08, "diagnostics", FunctionEffect::Unknown, false},  // sub-function 01 restarts the device
    {0x0B, "get_comm_event_counter", FunctionEffect::Reads, false},
    {0x0C, "get_comm_event_log", FunctionEffect::Reads, false},
    {0x0F, "write_multiple_coils", FunctionEffect::Writes, true},
    {0x10, "write_multiple_registers", FunctionEffect::Writes, true},
    {0x11, "report_server_id", FunctionEffect::Reads, false},
    {0x14, "read_file_record", FunctionEffect::Reads, false},
    {0x15, "write_file_record", FunctionEffect::Writes, false},
    {0x16, "mask_write_register", FunctionEffect::Writes, false},
    {0x17, "read_write_multiple_registers", FunctionEffect::Writes, true},
    {0x18, "read_fifo_queue", FunctionEffect::Reads, false},
    {0x2B, "encapsulated_interface_transport", FunctionEffect::Unknown, false},  // MEI 0x0D carries anything
}};

// nullptr when `code` is not a public Modbus function.
constexpr const ModbusFunction* find_modbus_function(std::uint8_t code) {
  for (const auto& function : kModbusFunctions) {
    if (function.code == code) return &function;
  }
  return nullptr;
}

// The effect of `code`; Unknown for codes not in the table.
constexpr FunctionEffect function_effect(std::uint8_t code) {
  const ModbusFunction* function = find_modbus_function(code);
  return function != nullptr ? function->effect : FunctionEffect::Unknown;
}

// Modbus Application Protocol v1.1b3 §7. `contract`: a code docs/PLC_GUIDE.md says the gateway
// answers with.
struct ModbusExceptionName {
  std::uint8_t code;
  std::string_view name;   // for messages
  std::string_view label;  // snake_case, for metrics labels
  bool contract;
};
inline constexpr std::array<ModbusExceptionName, 9> kModbusExceptionNames{{
    {0x01, "illegal function", "illegal_function", true},
    {0x02, "illegal data address", "illegal_data_address", true},
    {0x03, "illegal data value", "illegal_data_value", true},
    {0x04, "server device failure", "server_device_failure", true},
    {0x05, "acknowledge", "acknowledge", false},
    {0x06, "server device busy", "server_device_busy", true},
    {0x08, "memory parity error", "memory_parity_error", false},
    {0x0A, "gateway path unavailable", "gateway_path_unavailable", true},
    {0x0B, "gateway target device failed to respond", "gateway_target_device_failed_to_respond", true},
}};

// nullptr when `code` is not a standard exception code.
constexpr const ModbusExceptionName* find_modbus_exception(std::uint8_t code) {
  for (const auto& entry : kModbusExceptionNames) {
    if (entry.code == code) return &entry;
  }
  return nullptr;
}

constexpr std::string_view modbus_exception_name(std::uint8_t code) {
  const ModbusExceptionName* entry = find_modbus_exception(code);
  return entry != nullptr ? entry->name : "unknown exception";
}

// FC03 of `count` registers from `address`.
inline std::vector<std::uint8_t> read_holding_registers_pdu(std::uint16_t address, std::uint16_t count) {
  return {function_code::kReadHoldingRegisters, static_cast<std::uint8_t>(address >> 8),
          static_cast<std::uint8_t>(address), static_cast<std::uint8_t>(count >> 8), static_cast<std::uint8_t>(count)};
}

// FC06 for one register, FC16 for more; `data` holds the registers high byte first (an even
// number of bytes, at most kWriteRegisters registers: the caller checks).
inline std::vector<std::uint8_t> write_registers_pdu(std::uint16_t address, std::span<const std::uint8_t> data) {
  const auto address_hi = static_cast<std::uint8_t>(address >> 8);
  const auto address_lo = static_cast<std::uint8_t>(address);
  if (data.size() == 2) return {function_code::kWriteSingleRegister, address_hi, address_lo, data[0], data[1]};
  // Sized once and filled in place (GCC 12 -O2 misreads an insert after a braced init as out of
  // bounds: -Warray-bounds).
  constexpr std::size_t kHeader = 6;
  std::vector<std::uint8_t> pdu(kHeader + data.size(), 0);
  pdu[0] = function_code::kWriteMultipleRegisters;
  pdu[1] = address_hi;
  pdu[2] = address_lo;
  pdu[4] = static_cast<std::uint8_t>(data.size() / 2);
  pdu[5] = static_cast<std::uint8_t>(data.size());
  for (std::size_t i = 0; i < data.size(); ++i) pdu[kHeader + i] = data[i];
  return pdu;
}

}  // namespace sms::protocol
