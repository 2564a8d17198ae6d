#include "gateway/service/modbus_request.h"

#include <optional>
#include <stdexcept>
#include <type_traits>

#include "protocol/modbus_tcp.h"

namespace sms::gateway {
namespace {

namespace fc = function_code;
namespace wire = protocol::tcp::exception_code;

// The exception's value is its byte on the wire (application protocol §7).
static_assert(static_cast<std::uint8_t>(ModbusException::IllegalFunction) == wire::kIllegalFunction);
static_assert(static_cast<std::uint8_t>(ModbusException::IllegalDataAddress) == wire::kIllegalDataAddress);
static_assert(static_cast<std::uint8_t>(ModbusException::IllegalDataValue) == wire::kIllegalDataValue);
static_assert(static_cast<std::uint8_t>(ModbusException::ServerDeviceFailure) == wire::kServerDeviceFailure);
static_assert(static_cast<std::uint8_t>(ModbusException::ServerDeviceBusy) == wire::kServerDeviceBusy);
static_assert(static_cast<std::uint8_t>(ModbusException::GatewayPathUnavailable) == wire::kGatewayPathUnavailable);
static_assert(static_cast<std::uint8_t>(ModbusException::GatewayTargetFailedToRespond) ==
              wire::kGatewayTargetFailedToRespond);

using Parsed = Expected<Request, ModbusException>;

// A PDU whose length or byte count does not fit its function: 0x03 (illegal data value).
Unexpected<ModbusException> malformed() { return unexpected(ModbusException::IllegalDataValue); }
std::uint16_t u16_at(std::span<const std::uint8_t> bytes, std::size_t offset) {
  return static_cast<std::uint16_t>((bytes[offset] << 8) | bytes[offset + 1]);
}

void append_u16(Bytes& out, std::uint16_t value) {
  out.push_back(static_cast<std::uint8_t>(value >> 8));
  out.push_back(static_cast<std::uint8_t>(value & 0xFF));
}

// A quantity is checked before its addresses, as the Modbus application protocol's diagrams do
// for every function: a quantity of 0 or over the function's limit is 0x03 (illegal data value);
// a range running past address 65535 is 0x02 (illegal data address).
std::optional<ModbusException> range_fault(std::uint16_t address, std::uint16_t count, std::uint16_t limit) {
  if (count < 1 || count > limit) return ModbusException::IllegalDataValue;
  if (std::uint32_t{address} + count > 0x10000) return ModbusException::IllegalDataAddress;
  return std::nullopt;
}

std::vector<std::uint16_t> registers_from(std::span<const std::uint8_t> bytes, std::uint16_t count) {
  std::vector<std::uint16_t> values(count);
  for (std::uint16_t i = 0; i < count; ++i) values[i] = u16_at(bytes, std::size_t{2} * i);
  return values;
}

Parsed parse_read_bits(std::uint8_t function, std::span<const std::uint8_t> body) {
  if (body.size() != 4) return malformed();
  ReadBitsRequest request{function, u16_at(body, 0), u16_at(body, 2)};
  if (const auto fault = range_fault(request.address, request.count, limits::kReadBits)) return unexpected(*fault);
  return Request{request};
}

Parsed parse_read_registers(std::uint8_t function, std::span<const std::uint8_t> body) {
  if (body.size() != 4) return malformed();
  ReadRegistersRequest request{function, u16_at(body, 0), u16_at(body, 2)};
  if (const auto fault = range_fault(request.address, request.count, limits::kReadRegisters)) {
    return unexpected(*fault);
  }
  return Request{request};
}

Parsed parse_write_single_coil(std::uint8_t /*function*/, std::span<const std::uint8_t> body) {
  if (body.size() != 4) return malformed();
  const std::uint16_t value = u16_at(body, 2);
  if (value != 0x0000 && value != 0xFF00) return malformed();
  return Request{WriteBitsRequest{fc::kWriteSingleCoil, u16_at(body, 0), {value == 0xFF00}}};
}

Parsed parse_write_single_register(std::uint8_t /*function*/, std::span<const std::uint8_t> body) {
  if (body.size() != 4) return malformed();
  return Request{WriteRegistersRequest{fc::kWriteSingleRegister, u16_at(body, 0), {u16_at(body, 2)}}};
}

Parsed parse_write_multiple_coils(std::uint8_t /*function*/, std::span<const std::uint8_t> body) {
  if (body.size() < 5) return malformed();
  const std::uint16_t address = u16_at(body, 0);
  const std::uint16_t count = u16_at(body, 2);
  if (const auto fault = range_fault(address, count, limits::kWriteBits)) return unexpected(*fault);
  const std::size_t byte_count = body[4];
  if (byte_count != (count + 7u) / 8u || body.size() != 5 + byte_count) return malformed();
  WriteBitsRequest request{fc::kWriteMultipleCoils, address, std::vector<bool>(count)};
  for (std::uint16_t i = 0; i < count; ++i) request.values[i] = ((body[5 + i / 8] >> (i % 8)) & 1) != 0;
  return Request{std::move(request)};
}

Parsed parse_write_multiple_registers(std::uint8_t /*function*/, std::span<const std::uint8_t> body) {
  if (body.size() < 5) return malformed();
  const std::uint16_t address = u16_at(body, 0);
  const std::uint16_t count = u16_at(body, 2);
  if (const auto fault = range_fault(address, count, limits::kWriteRegisters)) return unexpected(*fault);
  const std::size_t byte_count = body[4];
  if (byte_count != std::size_t{2} * count || body.size() != 5 + byte_count) return malformed();
  return Request{WriteRegistersRequest{fc::kWriteMultipleRegisters, address, registers_from(body.subspan(5), count)}};
}

Parsed parse_read_write_registers(std::uint8_t /*function*/, std::span<const std::uint8_t> body) {
  if (body.size() < 9) return malformed();
  ReadRegistersRequest read{fc::kReadWriteMultipleRegisters, u16_at(body, 0), u16_at(body, 2)};
  const std::uint16_t write_address = u16_at(body, 4);
  const std::uint16_t write_count = u16_at(body, 6);
  if (const auto fault = range_fault(read.address, read.count, limits::kReadWriteRead)) return unexpected(*fault);
  if (const auto fault = range_fault(write_address, write_count, limits::kReadWriteWrite)) return unexpected(*fault);
  const std::size_t byte_count = body[8];
  if (byte_count != std::size_t{2} * write_count || body.size() != 9 + byte_count) return malformed();
  WriteRegistersRequest write{fc::kReadWriteMultipleRegisters, write_address,
                              registers_from(body.subspan(9), write_count)};
  return Request{ReadWriteRegistersRequest{read, std::move(write)}};
}

struct FunctionParser {
  std::uint8_t function;
  Parsed (*parse)(std::uint8_t function, std::span<const std::uint8_t> body);
};
// The function codes the gateway serves; anything else is answered 0x01.
constexpr FunctionParser kParsers[] = {
    {fc::kReadCoils, parse_read_bits},
    {fc::kReadDiscreteInputs, parse_read_bits},
    {fc::kReadHoldingRegisters, parse_read_registers},
    {fc::kReadInputRegisters, parse_read_registers},
    {fc::kWriteSingleCoil, parse_write_single_coil},
    {fc::kWriteSingleRegister, parse_write_single_register},
    {fc::kWriteMultipleCoils, parse_write_multiple_coils},
    {fc::kWriteMultipleRegisters, parse_write_multiple_registers},
    {fc::kReadWriteMultipleRegisters, parse_read_write_registers},
};

}  // namespace

Expected<Request, ModbusException> parse_request(std::span<const std::uint8_t> pdu) {
  if (pdu.empty()) return malformed();
  for (const auto& entry : kParsers) {
    if (entry.function == pdu[0]) return entry.parse(pdu[0], pdu.subspan(1));
  }
  return unexpected(ModbusException::IllegalFunction);
}

std::uint8_t function_of(const Request& request) {
  return std::visit(
      [](const auto& r) -> std::uint8_t {
        if constexpr (std::is_same_v<std::decay_t<decltype(r)>, ReadWriteRegistersRequest>) {
          return r.read.function;
        } else {
          return r.function;
        }
      },
      request);
}

Bytes bits_response(std::uint8_t function, const std::vector<bool>& values) {
  const std::size_t byte_count = (values.size() + 7) / 8;
  if (byte_count > 250) throw std::length_error("bits_response: more than 2000 bits");
  Bytes out(2 + byte_count, 0);
  out[0] = function;
  out[1] = static_cast<std::uint8_t>(byte_count);
  for (std::size_t i = 0; i < values.size(); ++i) {
    if (values[i]) out[2 + i / 8] |= static_cast<std::uint8_t>(1u << (i % 8));
  }
  return out;
}

Bytes registers_response(std::uint8_t function, std::span<const std::uint16_t> values) {
  if (values.size() > limits::kReadRegisters) throw std::length_error("registers_response: more than 125 registers");
  Bytes out;
  out.reserve(2 + 2 * values.size());
  out.push_back(function);
  out.push_back(static_cast<std::uint8_t>(2 * values.size()));
  for (const std::uint16_t value : values) append_u16(out, value);
  return out;
}

Bytes write_response(const WriteBitsRequest& request) {
  Bytes out{request.function};
  append_u16(out, request.address);
  if (request.function == fc::kWriteSingleCoil) {
    append_u16(out, request.values.at(0) ? 0xFF00 : 0x0000);
  } else {
    append_u16(out, static_cast<std::uint16_t>(request.values.size()));
  }
  return out;
}

Bytes write_response(const WriteRegistersRequest& request) {
  Bytes out{request.function};
  append_u16(out, request.address);
  if (request.function == fc::kWriteSingleRegister) {
    append_u16(out, request.values.at(0));
  } else {
    append_u16(out, static_cast<std::uint16_t>(request.values.size()));
  }
  return out;
}

Bytes request_pdu(const Request& request) {
  Bytes out;
  const auto header = [&out](std::uint8_t function, std::uint16_t address, std::uint16_t count) {
    out.push_back(function);
    append_u16(out, address);
    append_u16(out, count);
  };
  std::visit(
      [&](const auto& r) {
        using T = std::decay_t<decltype(r)>;
        if constexpr (std::is_same_v<T, ReadBitsRequest> || std::is_same_v<T, ReadRegistersRequest>) {
          header(r.function, r.address, r.count);
        } else if constexpr (std::is_same_v<T, WriteBitsRequest>) {
          if (r.function == fc::kWriteSingleCoil) {
            out = write_response(r);  // FC05's answer echoes its request
            return;
          }
          header(r.function, r.address, static_cast<std::uint16_t>(r.values.size()));
          out.push_back(static_cast<std::uint8_t>((r.values.size() + 7) / 8));
          for (std::size_t i = 0; i < r.values.size(); i += 8) {
            std::uint8_t byte = 0;
            for (std::size_t b = 0; b < 8 && i + b < r.values.size(); ++b) byte |= r.values[i + b] ? 1u << b : 0u;
            out.push_back(byte);
          }
        } else if constexpr (std::is_same_v<T, WriteRegistersRequest>) {
          if (r.function == fc::kWriteSingleRegister) {
            out = write_response(r);  // FC06's answer echoes its request
            return;
          }
          header(r.function, r.address, static_cast<std::uint16_t>(r.values.size()));
          out.push_back(static_cast<std::uint8_t>(r.values.size() * 2));
          for (const auto value : r.values) append_u16(out, value);
        } else {
          header(fc::kReadWriteMultipleRegisters, r.read.address, r.read.count);
          append_u16(out, r.write.address);
          append_u16(out, static_cast<std::uint16_t>(r.write.values.size()));
          out.push_back(static_cast<std::uint8_t>(r.write.values.size() * 2));
          for (const auto value : r.write.values) append_u16(out, value);
        }
      },
      request);
  return out;
}

Bytes exception_response(std::uint8_t function, ModbusException code) {
  return protocol::tcp::exception_pdu(function, static_cast<std::uint8_t>(code));
}

}  // namespace sms::gateway
