#include "gateway/units/bus_faults.h"

#include <array>
#include <stdexcept>

namespace sms::gateway {
namespace {

using modbus_map::ModbusException;

struct BusStatusException {
  BusStatus status;
  ModbusException exception;
};
constexpr std::array kBusStatusExceptions{
    BusStatusException{BusStatus::Timeout,
                       ModbusException::GatewayTargetFailedToRespond},                  // no answer after the retries
    BusStatusException{BusStatus::Corrupt, ModbusException::ServerDeviceFailure},       // replies stayed corrupt
    BusStatusException{BusStatus::ServoRefused, ModbusException::ServerDeviceFailure},  // its ERROR byte refused it
    BusStatusException{BusStatus::BusDown, ModbusException::GatewayPathUnavailable},
    BusStatusException{BusStatus::QueueFull, ModbusException::ServerDeviceBusy},
    BusStatusException{BusStatus::Cancelled, ModbusException::GatewayPathUnavailable},  // the gateway is stopping
    BusStatusException{BusStatus::Dropped, ModbusException::ServerDeviceFailure},  // failed inside; nothing was done
    BusStatusException{BusStatus::MotionBlocked, ModbusException::ServerDeviceFailure},  // the safety rules at the wire
};

}  // namespace

ModbusException fault_from(BusStatus status) {
  for (const auto& entry : kBusStatusExceptions) {
    if (entry.status == status) return entry.exception;
  }
  throw std::logic_error("fault_from(BusStatus::Ok): a successful bus operation is not a fault");
}

}  // namespace sms::gateway
