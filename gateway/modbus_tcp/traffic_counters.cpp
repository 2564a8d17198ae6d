#include "gateway/modbus_tcp/traffic_counters.h"

#include "protocol/modbus_tcp.h"

namespace sms::gateway {
namespace {

constexpr auto kRelaxed = std::memory_order_relaxed;

}  // namespace

void ModbusTrafficCounters::count_request(std::span<const std::uint8_t> pdu) {
  if (pdu.empty()) return;
  requests_by_function_[pdu[0]].fetch_add(1, kRelaxed);
}

void ModbusTrafficCounters::count_response(std::span<const std::uint8_t> pdu) {
  responses_.fetch_add(1, kRelaxed);
  if (const auto code = protocol::tcp::exception_code_of(pdu)) exceptions_by_code_[*code].fetch_add(1, kRelaxed);
}

ModbusTrafficSnapshot ModbusTrafficCounters::snapshot() const {
  ModbusTrafficSnapshot snapshot;
  for (std::size_t i = 0; i < snapshot.requests_by_function.size(); ++i) {
    snapshot.requests_by_function[i] = requests_by_function_[i].load(kRelaxed);
    snapshot.exceptions_by_code[i] = exceptions_by_code_[i].load(kRelaxed);
  }
  snapshot.responses = responses_.load(kRelaxed);
  return snapshot;
}

}  // namespace sms::gateway
