#include "protocol/bus_protocol.h"

#include <array>
#include <utility>

namespace sms::protocol {
namespace {

struct BusProtocolName {
  BusProtocol protocol;
  std::string_view name;
};

constexpr std::array<BusProtocolName, 3> kBusProtocolNames{{
    {BusProtocol::Feetech, "feetech"},
    {BusProtocol::D55d, "d55d"},
    {BusProtocol::ModbusRtu, "modbus-rtu"},
}};

}  // namespace

std::string_view to_string(BusProtocol protocol) {
  for (const auto& entry : kBusProtocolNames) {
    if (entry.protocol == protocol) return entry.name;
  }
  return "unknown";
}

std::optional<BusProtocol> bus_protocol_from_string(std::string_view name) {
  for (const auto& entry : kBusProtocolNames) {
    if (entry.name == name) return entry.protocol;
  }
  return std::nullopt;
}

}  // namespace sms::protocol
