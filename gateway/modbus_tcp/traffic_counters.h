#pragma once
// Modbus TCP traffic as /metrics shows it: requests by function code and answers by exception
// code, counted by the TCP sessions.
#include <array>
#include <atomic>
#include <cstdint>
#include <span>

namespace sms::gateway {

struct ModbusTrafficSnapshot {
  std::array<std::uint64_t, 256> requests_by_function{};  // index: a request PDU's function code
  std::array<std::uint64_t, 256> exceptions_by_code{};    // index: an exception answer's code
  std::uint64_t responses = 0;                            // answers sent, normal and exception
};

// Requests by function code and answers by exception code, counted by the Modbus TCP sessions
// (any thread; relaxed atomics: each counter is exact, a snapshot is not one instant).
class ModbusTrafficCounters {
 public:
  // The request PDU as received (function code first); an empty PDU is not counted.
  void count_request(std::span<const std::uint8_t> pdu);
  // The answer PDU as sent; an exception answer (function | 0x80, code) also counts its code.
  void count_response(std::span<const std::uint8_t> pdu);

  ModbusTrafficSnapshot snapshot() const;

 private:
  std::array<std::atomic<std::uint64_t>, 256> requests_by_function_{};
  std::array<std::atomic<std::uint64_t>, 256> exceptions_by_code_{};
  std::atomic<std::uint64_t> responses_{0};
};

}  // namespace sms::gateway
