// Request PDU parsing, response PDU building and the exception code table. Expected bytes are
// written out by hand from the Modbus application protocol v1.1b3 §6.
#include <gtest/gtest.h>

#include "gateway/service/modbus_request.h"

namespace sms::gateway {
namespace {

Expected<Request, ModbusException> parse(std::initializer_list<std::uint8_t> pdu) {
  const Bytes bytes(pdu);
  return parse_request(bytes);
}

TEST(ModbusRequest, ReadHoldingRegisters) {
  const auto request = parse({0x03, 0x00, 0x38, 0x00, 0x0F});
  ASSERT_TRUE(request);
  const auto& read = std::get<ReadRegistersRequest>(*request);
  EXPECT_EQ(read.function, 0x03);
  EXPECT_EQ(read.address, 56);
  EXPECT_EQ(read.count, 15);
}

TEST(ModbusRequest, ReadInputRegistersAndBitSpaces) {
  EXPECT_EQ(std::get<ReadRegistersRequest>(*parse({0x04, 0x03, 0xE8, 0x00, 0x08})).address, 1000);
  const auto coils = std::get<ReadBitsRequest>(*parse({0x01, 0x00, 0x28, 0x00, 0x01}));
  EXPECT_EQ(coils.function, 0x01);
  EXPECT_EQ(coils.address, 40);
  EXPECT_EQ(coils.count, 1);
  const auto inputs = std::get<ReadBitsRequest>(*parse({0x02, 0x03, 0xF0, 0x00, 0x01}));
  EXPECT_EQ(inputs.function, 0x02);
  EXPECT_EQ(inputs.address, 1008);
}

TEST(ModbusRequest, WriteSingleCoilAcceptsOnlyFF00AndZero) {
  EXPECT_EQ(std::get<WriteBitsRequest>(*parse({0x05, 0x00, 0x28, 0xFF, 0x00})).values, std::vector<bool>{true});
  EXPECT_EQ(std::get<WriteBitsRequest>(*parse({0x05, 0x00, 0x28, 0x00, 0x00})).values, std::vector<bool>{false});
  EXPECT_EQ(parse({0x05, 0x00, 0x28, 0x00, 0x01}).error(), ModbusException::IllegalDataValue);
  EXPECT_EQ(parse({0x05, 0x00, 0x28, 0xFF, 0xFF}).error(), ModbusException::IllegalDataValue);
}

TEST(ModbusRequest, WriteSingleRegister) {
  const auto write = std::get<WriteRegistersRequest>(*parse({0x06, 0x00, 0x2A, 0xFC, 0x18}));
  EXPECT_EQ(write.function, 0x06);
  EXPECT_EQ(write.address, 42);
  EXPECT_EQ(write.values, std::vector<std::uint16_t>{0xFC18});
}

TEST(ModbusRequest, WriteMultipleCoilsUnpacksLowBitFirst) {
  // 10 coils from 20: 0xCD = 1100 1101 -> coils 20,22,23,26,27 on; 0x01 -> coil 28 on.
  const auto write = std::get<WriteBitsRequest>(*parse({0x0F, 0x00, 0x14, 0x00, 0x0A, 0x02, 0xCD, 0x01}));
  EXPECT_EQ(write.address, 20);
  EXPECT_EQ(write.values, (std::vector<bool>{true, false, true, true, false, false, true, true, true, false}));
}

TEST(ModbusRequest, WriteMultipleRegisters) {
  const auto write =
      std::get<WriteRegistersRequest>(*parse({0x10, 0x00, 0x2A, 0x00, 0x03, 0x06, 0x08, 0x00, 0x00, 0x00, 0x03, 0xE8}));
  EXPECT_EQ(write.address, 42);
  EXPECT_EQ(write.values, (std::vector<std::uint16_t>{2048, 0, 1000}));
}

TEST(ModbusRequest, ReadWriteMultipleRegisters) {
  const auto both = std::get<ReadWriteRegistersRequest>(
      *parse({0x17, 0x00, 0x38, 0x00, 0x02, 0x00, 0x2A, 0x00, 0x01, 0x02, 0x04, 0x00}));
  EXPECT_EQ(both.read.function, 0x17);
  EXPECT_EQ(both.read.address, 56);
  EXPECT_EQ(both.read.count, 2);
  EXPECT_EQ(both.write.address, 42);
  EXPECT_EQ(both.write.values, std::vector<std::uint16_t>{0x0400});
}

TEST(ModbusRequest, UnsupportedFunctionCodes) {
  for (const std::uint8_t function : {0x00, 0x07, 0x08, 0x11, 0x14, 0x16, 0x2B, 0x41, 0x80, 0xFF}) {
    const auto request = parse({function, 0x00, 0x00, 0x00, 0x01});
    ASSERT_FALSE(request) << int(function);
    EXPECT_EQ(request.error(), ModbusException::IllegalFunction) << int(function);
  }
}

// The Modbus application protocol checks the quantity first, 0x03 outside 1..limit, then the
// addresses, 0x02.
TEST(ModbusRequest, AQuantityOfZeroOrOverTheLimitIsAnIllegalDataValue) {
  EXPECT_TRUE(parse({0x01, 0x00, 0x00, 0x07, 0xD0}));  // 2000 bits
  EXPECT_EQ(parse({0x01, 0x00, 0x00, 0x07, 0xD1}).error(), ModbusException::IllegalDataValue);
  EXPECT_EQ(parse({0x02, 0x00, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
  EXPECT_TRUE(parse({0x03, 0x00, 0x00, 0x00, 0x7D}));  // 125 registers
  EXPECT_EQ(parse({0x03, 0x00, 0x00, 0x00, 0x7E}).error(), ModbusException::IllegalDataValue);
  EXPECT_EQ(parse({0x04, 0x00, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
  // 124 registers (248 bytes) cannot be written in one FC16: limit 123.
  Bytes fc16{0x10, 0x00, 0x00, 0x00, 0x7C, 0xF8};
  fc16.resize(fc16.size() + 248, 0);
  EXPECT_EQ(parse_request(fc16).error(), ModbusException::IllegalDataValue);
  Bytes fc15{0x0F, 0x00, 0x00, 0x07, 0xB1, 0xF7};  // 1969 coils > 1968
  fc15.resize(fc15.size() + 247, 0);
  EXPECT_EQ(parse_request(fc15).error(), ModbusException::IllegalDataValue);
  // FC23: write part at most 121 registers.
  Bytes fc23{0x17, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x7A, 0xF4};
  fc23.resize(fc23.size() + 244, 0);
  EXPECT_EQ(parse_request(fc23).error(), ModbusException::IllegalDataValue);
  // FC16 and FC15 with quantity 0 (byte count 0).
  EXPECT_EQ(parse({0x10, 0x00, 0x00, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
  EXPECT_EQ(parse({0x0F, 0x00, 0x00, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
  // A quantity of 0 at an address that would also run past 65535: the quantity is checked first.
  EXPECT_EQ(parse({0x03, 0xFF, 0xFF, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
}

TEST(ModbusRequest, ARangePastAddress65535IsAnIllegalDataAddress) {
  EXPECT_TRUE(parse({0x03, 0xFF, 0xFF, 0x00, 0x01}));
  EXPECT_EQ(parse({0x03, 0xFF, 0xFF, 0x00, 0x02}).error(), ModbusException::IllegalDataAddress);
  EXPECT_EQ(parse({0x01, 0xFF, 0xF0, 0x00, 0x11}).error(), ModbusException::IllegalDataAddress);
}

TEST(ModbusRequest, MalformedPdus) {
  EXPECT_EQ(parse({0x03, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);              // short
  EXPECT_EQ(parse({0x03, 0x00, 0x00, 0x00, 0x01, 0x00}).error(), ModbusException::IllegalDataValue);  // long
  EXPECT_EQ(parse({0x06, 0x00, 0x00, 0x00}).error(), ModbusException::IllegalDataValue);
  EXPECT_EQ(parse({0x10, 0x00, 0x00, 0x00, 0x02, 0x02, 0x00, 0x01}).error(),
            ModbusException::IllegalDataValue);  // 2 regs, 2 bytes
  EXPECT_EQ(parse({0x10, 0x00, 0x00, 0x00, 0x01, 0x02, 0x00}).error(),
            ModbusException::IllegalDataValue);  // bytes missing
  EXPECT_EQ(parse({0x0F, 0x00, 0x00, 0x00, 0x09, 0x01, 0xFF}).error(),
            ModbusException::IllegalDataValue);  // 9 coils in 1 byte
  EXPECT_EQ(parse({0x17, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x02, 0x00}).error(),
            ModbusException::IllegalDataValue);
}

// request_pdu is parse_request's inverse for every kind the parser takes.
TEST(ModbusRequest, RequestPduParsesBackToTheSameRequest) {
  const std::vector<Request> requests{
      ReadBitsRequest{0x01, 10, 17},
      ReadBitsRequest{0x02, 1008, 1},
      ReadRegistersRequest{0x03, 0, 125},
      ReadRegistersRequest{0x04, 1000, 8},
      WriteBitsRequest{0x05, 1, {true}},
      WriteBitsRequest{0x05, 2, {false}},
      WriteBitsRequest{0x0F, 3, {true, false, true, true, false, false, false, true, true}},
      WriteRegistersRequest{0x06, 42, {0xFFFE}},
      WriteRegistersRequest{0x10, 40, {1, 2, 3}},
      ReadWriteRegistersRequest{ReadRegistersRequest{0x17, 56, 4}, WriteRegistersRequest{0x17, 42, {7, 8}}},
  };
  for (const auto& request : requests) {
    const auto pdu = request_pdu(request);
    const auto parsed = parse_request(pdu);
    ASSERT_TRUE(parsed) << "function " << int(function_of(request));
    EXPECT_EQ(request_pdu(*parsed), pdu) << "function " << int(function_of(request));
    EXPECT_EQ(function_of(*parsed), function_of(request));
  }
  EXPECT_EQ(request_pdu(ReadRegistersRequest{0x04, 0x0100, 8}), (Bytes{0x04, 0x01, 0x00, 0x00, 0x08}));
  EXPECT_EQ(request_pdu(WriteRegistersRequest{0x06, 42, {0x1234}}), (Bytes{0x06, 0x00, 0x2A, 0x12, 0x34}));
  EXPECT_EQ(request_pdu(WriteBitsRequest{0x05, 1, {true}}), (Bytes{0x05, 0x00, 0x01, 0xFF, 0x00}));
}

TEST(ModbusResponse, BitsArePackedLowBitFirst) {
  EXPECT_EQ(bits_response(0x01, {true, false, true, true, false, false, true, true, true, false}),
            (Bytes{0x01, 0x02, 0xCD, 0x01}));
  EXPECT_EQ(bits_response(0x02, {false}), (Bytes{0x02, 0x01, 0x00}));
}

TEST(ModbusResponse, RegistersAreHighByteFirst) {
  const std::uint16_t values[] = {0x0518, 0xFC18};
  EXPECT_EQ(registers_response(0x03, values), (Bytes{0x03, 0x04, 0x05, 0x18, 0xFC, 0x18}));
}

TEST(ModbusResponse, WritesEchoOrCount) {
  EXPECT_EQ(write_response(WriteBitsRequest{0x05, 40, {true}}), (Bytes{0x05, 0x00, 0x28, 0xFF, 0x00}));
  EXPECT_EQ(write_response(WriteBitsRequest{0x0F, 20, std::vector<bool>(10)}), (Bytes{0x0F, 0x00, 0x14, 0x00, 0x0A}));
  EXPECT_EQ(write_response(WriteRegistersRequest{0x06, 42, {0xFC18}}), (Bytes{0x06, 0x00, 0x2A, 0xFC, 0x18}));
  EXPECT_EQ(write_response(WriteRegistersRequest{0x10, 42, {1, 2, 3}}), (Bytes{0x10, 0x00, 0x2A, 0x00, 0x03}));
}

// The exception's value is the byte the client gets (docs/PLC_GUIDE.md "Exceptions").
TEST(ModbusException, ResponsesCarryTheContractsCodes) {
  EXPECT_EQ(exception_response(0x03, ModbusException::IllegalFunction), (Bytes{0x83, 0x01}));
  EXPECT_EQ(exception_response(0x06, ModbusException::IllegalDataAddress), (Bytes{0x86, 0x02}));
  EXPECT_EQ(exception_response(0x06, ModbusException::IllegalDataValue), (Bytes{0x86, 0x03}));
  EXPECT_EQ(exception_response(0x10, ModbusException::ServerDeviceFailure), (Bytes{0x90, 0x04}));
  EXPECT_EQ(exception_response(0x10, ModbusException::ServerDeviceBusy), (Bytes{0x90, 0x06}));
  EXPECT_EQ(exception_response(0x03, ModbusException::GatewayPathUnavailable), (Bytes{0x83, 0x0A}));
  EXPECT_EQ(exception_response(0x10, ModbusException::GatewayTargetFailedToRespond), (Bytes{0x90, 0x0B}));
}

}  // namespace
}  // namespace sms::gateway
