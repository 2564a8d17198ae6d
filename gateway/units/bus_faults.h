#pragma once
// The Modbus exception a failed bus operation is answered with (docs/PLC_GUIDE.md "Exceptions"):
// the one translation into the gateway's exception vocabulary (ModbusException) that is not the
// register map's or the request parser's own, kept with the units that run bus operations so
// gateway/service/ and the TCP side do not depend on the buses.
#include "gateway/bus/bus_operations.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

// `status` must not be BusStatus::Ok.
modbus_map::ModbusException fault_from(BusStatus status);

}  // namespace sms::gateway
