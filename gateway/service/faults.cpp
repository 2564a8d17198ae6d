#include "gateway/service/faults.h"

#include <array>
#include <stdexcept>
#include <string>

#include "protocol/modbus_tcp.h"

namespace sms::gateway {
namespace {

namespace code = protocol::tcp::exception_code;

constexpr std::array kFaults{
    FaultSpec{Fault::UnsupportedFunction, code::kIllegalFunction, "function code not supported"},
    FaultSpec{Fault::BadAddress, code::kIllegalDataAddress,
              "address not served (no field, read-only, beyond the table)"},
    FaultSpec{Fault::QuantityOverLimit, code::kIllegalDataAddress, "quantity outside the Modbus limits"},
    FaultSpec{Fault::BadValue, code::kIllegalDataValue, "value outside the field's range"},
    FaultSpec{Fault::MalformedRequest, code::kIllegalDataValue, "request PDU malformed for its function"},
    FaultSpec{Fault::ServoRefused, code::kServerDeviceFailure, "the servo refused the instruction"},
    FaultSpec{Fault::ServoCorrupt, code::kServerDeviceFailure, "the servo's replies stayed corrupt"},
    FaultSpec{Fault::QueueFull, code::kServerDeviceBusy, "the bus's request queue is full"},
    FaultSpec{Fault::UnknownUnit, code::kGatewayPathUnavailable, "unknown unit"},
    FaultSpec{Fault::BusDown, code::kGatewayPathUnavailable, "the unit's bus is down"},
    FaultSpec{Fault::GatewayStopping, code::kGatewayPathUnavailable, "the gateway is stopping"},
    FaultSpec{Fault::ServoTimeout, code::kGatewayTargetFailedToRespond, "the servo did not answer"},
    FaultSpec{Fault::MotionBlocked, code::kServerDeviceFailure, "motion refused by the safety rules"},
    FaultSpec{Fault::InternalError, code::kServerDeviceFailure, "the gateway failed inside; nothing was done"},
};

constexpr bool faults_in_enum_order() {
  for (std::size_t i = 0; i < kFaults.size(); ++i) {
    if (static_cast<std::size_t>(kFaults[i].fault) != i) return false;
  }
  return true;
}
static_assert(faults_in_enum_order(), "kFaults is indexed by Fault");

struct MapExceptionFault {
  modbus_map::ModbusException code;
  Fault fault;
};
constexpr std::array kMapExceptionFaults{
    MapExceptionFault{modbus_map::ModbusException::IllegalFunction, Fault::UnsupportedFunction},
    MapExceptionFault{modbus_map::ModbusException::IllegalDataAddress, Fault::BadAddress},
    MapExceptionFault{modbus_map::ModbusException::IllegalDataValue, Fault::BadValue},
    MapExceptionFault{modbus_map::ModbusException::ServerDeviceFailure, Fault::ServoCorrupt},
    MapExceptionFault{modbus_map::ModbusException::ServerDeviceBusy, Fault::QueueFull},
    MapExceptionFault{modbus_map::ModbusException::GatewayPathUnavailable, Fault::BusDown},
    MapExceptionFault{modbus_map::ModbusException::GatewayTargetFailedToRespond, Fault::ServoTimeout},
};

const FaultSpec& spec(Fault fault) {
  const auto index = static_cast<std::size_t>(fault);
  if (index >= kFaults.size()) throw std::out_of_range("Fault " + std::to_string(index) + " has no exception code");
  return kFaults[index];
}

}  // namespace

std::span<const FaultSpec> fault_table() { return kFaults; }

std::uint8_t exception_code(Fault fault) { return spec(fault).exception_code; }

std::string_view to_string(Fault fault) { return spec(fault).meaning; }

Fault fault_from(modbus_map::ModbusException code) {
  for (const auto& entry : kMapExceptionFaults) {
    if (entry.code == code) return entry.fault;
  }
  throw std::logic_error("fault_from: Modbus exception " + std::to_string(static_cast<int>(code)) + " has no Fault");
}

}  // namespace sms::gateway
