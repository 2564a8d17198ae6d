#include "gateway/bus/bus_engine.h"

#include <stdexcept>
#include <string>

#include "gateway/bus/engine_core.h"
#include "gateway/bus/packet_transactor.h"
#include "gateway/bus/rtu_transactor.h"

namespace sms::gateway {

// Both transactors have the whole face the engine core is written against (transactor.h).
static_assert(BusTransactor<PacketTransactor>, "PacketTransactor must satisfy BusTransactor (transactor.h)");
static_assert(BusTransactor<RtuTransactor>, "RtuTransactor must satisfy BusTransactor (transactor.h)");

std::string_view to_string(BusStatus status) {
  switch (status) {
    case BusStatus::Ok: return "ok";
    case BusStatus::Timeout: return "timeout";
    case BusStatus::Corrupt: return "corrupt";
    case BusStatus::ServoRefused: return "servo refused";
    case BusStatus::BusDown: return "bus down";
    case BusStatus::QueueFull: return "queue full";
    case BusStatus::Cancelled: return "cancelled";
    case BusStatus::Dropped: return "dropped";
    case BusStatus::MotionBlocked: return "motion blocked";
  }
  return "?";
}

MotionEpoch motion_epoch_of(const BusOp& op) {
  return std::visit(
      [](const auto& o) -> MotionEpoch {
        if constexpr (requires { o.motion_epoch; }) {
          return o.motion_epoch;
        } else {
          return 0;
        }
      },
      op);
}

std::unique_ptr<BusEngine> make_bus_engine(BusSettings settings, const config::ModbusRtuOptions& modbus_rtu) {
  const auto timing = [](const BusSettings& bus) {
    return TransactionTiming{bus.response_timeout, "bus " + bus.name + ": "};
  };
  switch (settings.protocol) {
    case protocol::BusProtocol::Feetech:
    case protocol::BusProtocol::D55d:
      return std::make_unique<EngineCore<PacketTransactor>>(
          std::move(settings), [&](const BusSettings& bus, BusCounters& counters) {
            auto transactor = std::make_unique<PacketTransactor>(bus.protocol, bus.serial, timing(bus), counters);
            transactor->set_monitor(bus.wire_monitor.get());
            return transactor;
          });
    case protocol::BusProtocol::ModbusRtu:
      return std::make_unique<EngineCore<RtuTransactor>>(
          std::move(settings), [&](const BusSettings& bus, BusCounters& counters) {
            auto transactor =
                std::make_unique<RtuTransactor>(RtuLineSettings{bus.serial, modbus_rtu}, timing(bus), counters);
            transactor->set_monitor(bus.wire_monitor.get());
            return transactor;
          });
  }
  throw std::invalid_argument("bus " + settings.name + ": unknown protocol");
}

}  // namespace sms::gateway
