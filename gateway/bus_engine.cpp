#include "gateway/bus_engine.h"

#include <stdexcept>
#include <string>

#include "gateway/packet_bus_engine.h"
#include "gateway/rtu_bus_engine.h"

namespace sms::gateway {

std::string_view to_string(BusStatus status) {
  switch (status) {
    case BusStatus::Ok: return "ok";
    case BusStatus::Timeout: return "timeout";
    case BusStatus::Corrupt: return "corrupt";
    case BusStatus::ServoRefused: return "servo refused";
    case BusStatus::BusDown: return "bus down";
    case BusStatus::QueueFull: return "queue full";
    case BusStatus::Cancelled: return "cancelled";
  }
  return "?";
}

std::unique_ptr<BusEngine> make_bus_engine(BusSettings settings, const config::ModbusRtuOptions& modbus_rtu) {
  switch (settings.protocol) {
    case protocol::BusProtocol::Feetech:
    case protocol::BusProtocol::D55d:
      return std::make_unique<PacketBusEngine>(std::move(settings));
    case protocol::BusProtocol::ModbusRtu:
      return std::make_unique<RtuBusEngine>(std::move(settings), modbus_rtu);
  }
  throw std::invalid_argument("bus " + settings.name + ": unknown protocol");
}

}  // namespace sms::gateway
