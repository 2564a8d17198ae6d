#pragma once
// A libmodbus TCP client for the tests and the benchmarks: the client a PLC programmer would use,
// so nothing here shares code with the gateway. Each call returns the values, or the Modbus
// exception code the gateway answered with (0 when the failure was not an exception).
#include <modbus/modbus.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

namespace sms::test {

template <typename T>
struct Answer {
  std::vector<T> values;
  int exception = 0;  // Modbus exception code; -1 for a transport error (errno in `error`)
  std::string error;
  bool ok() const { return exception == 0; }
  // The values, or std::runtime_error naming `request` and the failure (setup and check reads).
  const std::vector<T>& or_throw(const std::string& request) const {
    if (!ok()) {
      throw std::runtime_error(request + ": " +
                               (error.empty() ? "Modbus exception " + std::to_string(exception) : error));
    }
    return values;
  }
};

class ModbusClient {
 public:
  ModbusClient(std::uint16_t port, int unit, std::chrono::milliseconds response_timeout = std::chrono::seconds{3}) {
    ctx_ = modbus_new_tcp("127.0.0.1", port);
    if (ctx_ == nullptr) throw std::runtime_error("modbus_new_tcp failed");
    const auto us = response_timeout.count() * 1000;
    modbus_set_response_timeout(ctx_, static_cast<std::uint32_t>(us / 1'000'000),
                                static_cast<std::uint32_t>(us % 1'000'000));
    if (modbus_connect(ctx_) != 0) {
      const std::string reason = modbus_strerror(errno);
      modbus_free(ctx_);
      throw std::runtime_error("connect to 127.0.0.1:" + std::to_string(port) + ": " + reason);
    }
    set_unit(unit);
  }
  ~ModbusClient() {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
  ModbusClient(const ModbusClient&) = delete;
  ModbusClient& operator=(const ModbusClient&) = delete;

  void set_unit(int unit) { modbus_set_slave(ctx_, unit); }
  modbus_t* context() { return ctx_; }

  Answer<std::uint16_t> read_holding(int address, int count) {
    return registers(count, [&](std::uint16_t* out) { return modbus_read_registers(ctx_, address, count, out); });
  }
  Answer<std::uint16_t> read_input(int address, int count) {
    return registers(count, [&](std::uint16_t* out) { return modbus_read_input_registers(ctx_, address, count, out); });
  }
  Answer<std::uint8_t> read_coils(int address, int count) {
    return bits(count, [&](std::uint8_t* out) { return modbus_read_bits(ctx_, address, count, out); });
  }
  Answer<std::uint8_t> read_discrete(int address, int count) {
    return bits(count, [&](std::uint8_t* out) { return modbus_read_input_bits(ctx_, address, count, out); });
  }
  Answer<std::uint16_t> write_register(int address, std::uint16_t value) {
    return status(modbus_write_register(ctx_, address, value));
  }
  Answer<std::uint16_t> write_registers(int address, const std::vector<std::uint16_t>& values) {
    return status(modbus_write_registers(ctx_, address, static_cast<int>(values.size()), values.data()));
  }
  Answer<std::uint16_t> write_coil(int address, bool value) { return status(modbus_write_bit(ctx_, address, value)); }
  Answer<std::uint16_t> write_coils(int address, const std::vector<std::uint8_t>& values) {
    return status(modbus_write_bits(ctx_, address, static_cast<int>(values.size()), values.data()));
  }
  Answer<std::uint16_t> write_and_read(int write_address, const std::vector<std::uint16_t>& values, int read_address,
                                       int read_count) {
    return registers(read_count, [&](std::uint16_t* out) {
      return modbus_write_and_read_registers(ctx_, write_address, static_cast<int>(values.size()), values.data(),
                                             read_address, read_count, out);
    });
  }
  // A raw request PDU (function code first); the answer PDU or the exception.
  Answer<std::uint8_t> raw(const std::vector<std::uint8_t>& pdu, int unit) {
    std::vector<std::uint8_t> request{static_cast<std::uint8_t>(unit)};
    request.insert(request.end(), pdu.begin(), pdu.end());
    if (modbus_send_raw_request(ctx_, request.data(), static_cast<int>(request.size())) < 0)
      return failure<std::uint8_t>();
    std::vector<std::uint8_t> reply(MODBUS_TCP_MAX_ADU_LENGTH);
    const int n = modbus_receive_confirmation(ctx_, reply.data());
    if (n < 0) return failure<std::uint8_t>();
    Answer<std::uint8_t> answer;
    answer.values.assign(reply.begin() + 7, reply.begin() + n);  // after the MBAP header
    if (!answer.values.empty() && (answer.values[0] & 0x80) != 0 && answer.values.size() == 2) {
      answer.exception = answer.values[1];
    }
    return answer;
  }

 private:
  template <typename T>
  static Answer<T> failure() {
    Answer<T> answer;
    if (errno > MODBUS_ENOBASE && errno < MODBUS_ENOBASE + 0x20) {
      answer.exception = errno - MODBUS_ENOBASE;
    } else {
      answer.exception = -1;
    }
    answer.error = modbus_strerror(errno);
    return answer;
  }
  template <typename F>
  static Answer<std::uint16_t> registers(int count, F call) {
    Answer<std::uint16_t> answer;
    answer.values.resize(static_cast<std::size_t>(std::max(count, 0)));
    if (call(answer.values.data()) < 0) return failure<std::uint16_t>();
    return answer;
  }
  template <typename F>
  static Answer<std::uint8_t> bits(int count, F call) {
    Answer<std::uint8_t> answer;
    answer.values.resize(static_cast<std::size_t>(std::max(count, 0)));
    if (call(answer.values.data()) < 0) return failure<std::uint8_t>();
    return answer;
  }
  static Answer<std::uint16_t> status(int rc) {
    if (rc < 0) return failure<std::uint16_t>();
    return {};
  }

  modbus_t* ctx_ = nullptr;
};

}  // namespace sms::test
