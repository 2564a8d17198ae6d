#include "gateway/bus/bus_engine.h"

#include <stdexcept>
#include <string>

#include <spdlog/spdlog.h>

#include "gateway/bus/engine_core.h"
#include "gateway/bus/packet_transactor.h"
#include "gateway/bus/rtu_transactor.h"

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
    case BusStatus::Dropped: return "dropped";
  }
  return "?";
}

BusStatus admission(bool accepting, bool bus_up, std::size_t queued, std::size_t queue_depth, Priority priority) {
  if (!accepting) return BusStatus::Cancelled;
  if (!bus_up) return BusStatus::BusDown;
  if (queued >= queue_depth && priority != Priority::Safety) return BusStatus::QueueFull;
  return BusStatus::Ok;
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

std::optional<BusResult> motion_refusal(const BusSettings& settings, MotionEpoch admitted) {
  if (admitted == 0 || !settings.motion_gate || settings.motion_gate->admits(admitted)) return std::nullopt;
  return BusResult{BusStatus::ServoRefused, 0, {},
                   "bus " + settings.name + ": motion write dropped: a watchdog trip or the e-stop stopped the bus "
                   "after it was accepted (README \"Safety\")"};
}

std::string refusal_detail(BusStatus refusal, const BusSettings& settings) {
  switch (refusal) {
    case BusStatus::Cancelled: return "bus " + settings.name + ": the bus engine is not running";
    case BusStatus::BusDown:
      return "bus " + settings.name + ": serial port " + settings.serial.device + " is not open (bus down)";
    case BusStatus::QueueFull:
      return "bus " + settings.name + ": " + std::to_string(settings.queue_depth) + " operations already queued";
    default: return "bus " + settings.name + ": " + std::string(to_string(refusal));
  }
}

void complete(const BusSettings& settings, Completion& done, BusResult result) {
  if (!done) return;
  try {
    done(std::move(result));
  } catch (const std::exception& error) {
    spdlog::error("bus {}: a completion handler threw: {}", settings.name, error.what());
  }
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
            auto transactor = std::make_unique<RtuTransactor>(RtuLineSettings{bus.serial, modbus_rtu}, timing(bus), counters);
            transactor->set_monitor(bus.wire_monitor.get());
            return transactor;
          });
  }
  throw std::invalid_argument("bus " + settings.name + ": unknown protocol");
}

}  // namespace sms::gateway
