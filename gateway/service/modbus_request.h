#pragma once
// Modbus request PDUs as the TCP side receives them, parsed into plain structs with every
// length checked before anything is touched (as libmodbus does), and the response PDUs
// built from plain values. Function codes of docs/PLC_GUIDE.md: 01 02 03 04 05 06 15 16 23.
#include <cstdint>
#include <span>
#include <variant>
#include <vector>

#include "modbus_map/register_map.h"
#include "protocol/expected.h"
#include "protocol/modbus_pdu.h"
#include "protocol/packet.h"

namespace sms::gateway {

using protocol::Bytes;
// The one exception vocabulary inside the gateway: every refusal, whichever part decides it (the
// request parser, the role policy, the register map, the bus, the safety rules), is a
// ModbusException; its byte is written only in the exception response (exception_response()).
using modbus_map::ModbusException;

namespace function_code = protocol::function_code;

// Quantity limits of the Modbus application protocol (v1.1b3 §6).
namespace limits = protocol::modbus_limits;

struct ReadBitsRequest {  // 01 coils, 02 discrete inputs
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::uint16_t count = 0;
};
struct ReadRegistersRequest {  // 03 holding, 04 input
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::uint16_t count = 0;
};
struct WriteBitsRequest {  // 05 single (one value), 15 multiple
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::vector<bool> values;
};
struct WriteRegistersRequest {  // 06 single (one value), 16 multiple
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::vector<std::uint16_t> values;
};
// 23: the write is performed before the read (application protocol §6.17).
struct ReadWriteRegistersRequest {
  ReadRegistersRequest read;
  WriteRegistersRequest write;
};

using Request = std::variant<ReadBitsRequest, ReadRegistersRequest, WriteBitsRequest, WriteRegistersRequest,
                             ReadWriteRegistersRequest>;

// IllegalFunction (0x01) for function codes not listed above; IllegalDataAddress (0x02) for a
// count of 0, over the function's limit, or running past address 65535; IllegalDataValue (0x03)
// for a PDU whose length or byte count does not match its function, or an FC05 value other than
// 0x0000 / 0xFF00.
Expected<Request, ModbusException> parse_request(std::span<const std::uint8_t> pdu);

std::uint8_t function_of(const Request& request);

// The PDU of a request: parse_request's inverse (internal clients such as the Sparkplug node ask
// the router as a Modbus client would). The request must be well-formed (quantities in range).
Bytes request_pdu(const Request& request);

// Response PDUs.
Bytes bits_response(std::uint8_t function, const std::vector<bool>& values);             // 01 02
Bytes registers_response(std::uint8_t function, std::span<const std::uint16_t> values);  // 03 04 23
// 05 06 echo the request; 15 16 answer address and quantity.
Bytes write_response(const WriteBitsRequest& request);
Bytes write_response(const WriteRegistersRequest& request);
Bytes exception_response(std::uint8_t function, ModbusException code);

}  // namespace sms::gateway
