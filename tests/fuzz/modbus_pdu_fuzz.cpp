// libFuzzer target: gateway::parse_request, the Modbus TCP request PDU parser every client PDU
// goes through (gateway/service/modbus_request.h), and the response builders its answers use. The
// whole input is one PDU, function code first.
//
// Invariants:
//   - a PDU is refused only as UnsupportedFunction (unknown code), QuantityOverLimit or
//     MalformedRequest, and its exception response is `function | 0x80, code`;
//   - a request it accepts re-encodes, by the Modbus application protocol's layouts written out
//     here, to the very PDU it came from (FC 15's unused padding bits aside), within the limits;
//   - the answer to an accepted request fits in one PDU: writes echo the first five bytes,
//     reads answer as many values as were asked for.
#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "fuzz_support.h"
#include "gateway/service/modbus_request.h"
#include "protocol/modbus_tcp.h"

namespace {

namespace gw = sms::gateway;
namespace tcp = sms::protocol::tcp;
using sms::fuzz::hex;
using sms::protocol::Bytes;

constexpr std::array<std::uint8_t, 9> kServedFunctions{0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x17};

void append_u16(Bytes& out, std::uint16_t value) {
  out.push_back(static_cast<std::uint8_t>(value >> 8));
  out.push_back(static_cast<std::uint8_t>(value & 0xFF));
}

// Modbus application protocol v1.1b3 §6, request layouts.
Bytes encode(const gw::ReadBitsRequest& r) {
  Bytes out{r.function};
  append_u16(out, r.address);
  append_u16(out, r.count);
  return out;
}
Bytes encode(const gw::ReadRegistersRequest& r) {
  Bytes out{r.function};
  append_u16(out, r.address);
  append_u16(out, r.count);
  return out;
}
Bytes encode(const gw::WriteBitsRequest& r) {
  Bytes out{r.function};
  append_u16(out, r.address);
  if (r.function == 0x05) {
    SMS_FUZZ_CHECK(r.values.size() == 1, "FC05 with " + std::to_string(r.values.size()) + " values");
    append_u16(out, r.values[0] ? 0xFF00 : 0x0000);
    return out;
  }
  append_u16(out, static_cast<std::uint16_t>(r.values.size()));
  out.push_back(static_cast<std::uint8_t>((r.values.size() + 7) / 8));
  for (std::size_t i = 0; i < r.values.size(); ++i) {
    if (i % 8 == 0) out.push_back(0);
    if (r.values[i]) out.back() |= static_cast<std::uint8_t>(1U << (i % 8));
  }
  return out;
}
void append_registers(Bytes& out, const std::vector<std::uint16_t>& values) {
  append_u16(out, static_cast<std::uint16_t>(values.size()));
  out.push_back(static_cast<std::uint8_t>(2 * values.size()));
  for (const std::uint16_t value : values) append_u16(out, value);
}
Bytes encode(const gw::WriteRegistersRequest& r) {
  Bytes out{r.function};
  append_u16(out, r.address);
  if (r.function == 0x06) {
    SMS_FUZZ_CHECK(r.values.size() == 1, "FC06 with " + std::to_string(r.values.size()) + " values");
    append_u16(out, r.values[0]);
    return out;
  }
  append_registers(out, r.values);
  return out;
}
Bytes encode(const gw::ReadWriteRegistersRequest& r) {
  Bytes out{0x17};
  append_u16(out, r.read.address);
  append_u16(out, r.read.count);
  append_u16(out, r.write.address);
  append_registers(out, r.write.values);
  return out;
}

// FC 15 packs coils into bytes; the bits past the quantity carry nothing.
Bytes without_coil_padding(std::span<const std::uint8_t> pdu) {
  Bytes out(pdu.begin(), pdu.end());
  if (out.size() >= 7 && out[0] == 0x0F) {
    const unsigned count = static_cast<unsigned>(out[3] << 8 | out[4]);
    if (count % 8 != 0) out.back() &= static_cast<std::uint8_t>((1U << (count % 8)) - 1);
  }
  return out;
}

bool in_range(std::uint16_t address, std::size_t count, std::size_t limit) {
  return count >= 1 && count <= limit && address + count <= 0x10000;
}

void check_accepted(std::span<const std::uint8_t> pdu, const gw::Request& request) {
  SMS_FUZZ_CHECK(gw::function_of(request) == pdu[0], "function_of differs from the PDU's code: " + hex(pdu));
  const Bytes encoded = std::visit([](const auto& r) { return encode(r); }, request);
  const Bytes original = without_coil_padding(pdu);
  SMS_FUZZ_CHECK(encoded == original, "parsed " + hex(pdu) + ", which re-encodes to " + hex(encoded));

  std::visit(
      [&](const auto& r) {
        using T = std::decay_t<decltype(r)>;
        if constexpr (std::is_same_v<T, gw::ReadBitsRequest>) {
          SMS_FUZZ_CHECK(in_range(r.address, r.count, 2000), "bit read outside the limits: " + hex(pdu));
          const Bytes answer = gw::bits_response(r.function, std::vector<bool>(r.count, true));
          SMS_FUZZ_CHECK(answer.size() == 2U + (r.count + 7U) / 8 && answer.size() <= tcp::kMaxPduSize,
                         "bits response of " + std::to_string(answer.size()) + " bytes");
        } else if constexpr (std::is_same_v<T, gw::ReadRegistersRequest>) {
          SMS_FUZZ_CHECK(in_range(r.address, r.count, 125), "register read outside the limits: " + hex(pdu));
          const std::vector<std::uint16_t> values(r.count, 0xBEEF);
          const Bytes answer = gw::registers_response(r.function, values);
          SMS_FUZZ_CHECK(answer.size() == 2U + 2U * r.count && answer.size() <= tcp::kMaxPduSize,
                         "registers response of " + std::to_string(answer.size()) + " bytes");
        } else if constexpr (std::is_same_v<T, gw::ReadWriteRegistersRequest>) {
          SMS_FUZZ_CHECK(
              in_range(r.read.address, r.read.count, 125) && in_range(r.write.address, r.write.values.size(), 121),
              "FC23 outside the limits: " + hex(pdu));
          const std::vector<std::uint16_t> values(r.read.count, 0xBEEF);
          SMS_FUZZ_CHECK(gw::registers_response(0x17, values).size() <= tcp::kMaxPduSize, "FC23 response too long");
        } else {
          const std::size_t limit = std::is_same_v<T, gw::WriteBitsRequest> ? 1968 : 123;
          SMS_FUZZ_CHECK(in_range(r.address, r.values.size(), limit), "write outside the limits: " + hex(pdu));
          const Bytes answer = gw::write_response(r);
          SMS_FUZZ_CHECK(answer.size() == 5 && std::equal(answer.begin(), answer.end(), pdu.begin()),
                         "write response " + hex(answer) + " is not the head of " + hex(pdu));
        }
      },
      request);
}

void check_refused(std::span<const std::uint8_t> pdu, gw::ModbusException fault) {
  const bool served =
      !pdu.empty() && std::find(kServedFunctions.begin(), kServedFunctions.end(), pdu[0]) != kServedFunctions.end();
  if (pdu.empty()) {
    SMS_FUZZ_CHECK(fault == gw::ModbusException::IllegalDataValue, "empty PDU not refused as malformed");
    return;
  }
  SMS_FUZZ_CHECK((fault == gw::ModbusException::IllegalFunction) == !served,
                 "0x01 (illegal function) must mean exactly an unserved code: " + hex(pdu));
  SMS_FUZZ_CHECK(fault == gw::ModbusException::IllegalFunction || fault == gw::ModbusException::IllegalDataAddress ||
                     fault == gw::ModbusException::IllegalDataValue,
                 "parse_request refused " + hex(pdu) + " with a fault no PDU can cause");
  const Bytes answer = gw::exception_response(pdu[0], fault);
  SMS_FUZZ_CHECK(answer.size() == 2 && answer[0] == (pdu[0] | 0x80) && answer[1] == static_cast<std::uint8_t>(fault) &&
                     tcp::exception_code_of(answer) == answer[1],
                 "exception response " + hex(answer) + " for " + hex(pdu));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::uint8_t> pdu(data, size);
  const auto parsed = gw::parse_request(pdu);
  if (parsed) {
    check_accepted(pdu, *parsed);
  } else {
    check_refused(pdu, parsed.error());
  }
  return 0;
}
