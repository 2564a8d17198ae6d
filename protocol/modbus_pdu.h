#pragma once
// Modbus function codes and quantity limits (Modbus application protocol v1.1b3 §6): the one
// home of both, shared by the register map, the TCP side, the RTU master and the tools. Header
// only, no code.
#include <cstdint>

namespace sms::protocol::function_code {

inline constexpr std::uint8_t kReadCoils = 0x01;
inline constexpr std::uint8_t kReadDiscreteInputs = 0x02;
inline constexpr std::uint8_t kReadHoldingRegisters = 0x03;
inline constexpr std::uint8_t kReadInputRegisters = 0x04;
inline constexpr std::uint8_t kWriteSingleCoil = 0x05;
inline constexpr std::uint8_t kWriteSingleRegister = 0x06;
inline constexpr std::uint8_t kWriteMultipleCoils = 0x0F;
inline constexpr std::uint8_t kWriteMultipleRegisters = 0x10;
inline constexpr std::uint8_t kReportServerId = 0x11;  // SMSMB servos answer it (SPEC §1.3)
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
