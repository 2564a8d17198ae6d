#pragma once
// The Fault a failed bus operation stands for (faults.h has the Faults and their exception
// codes; this is the bus side of the table, kept with the units that run bus operations so the
// Modbus TCP side does not depend on the buses).
#include "gateway/bus/bus_operations.h"
#include "gateway/service/faults.h"

namespace sms::gateway {

// `status` must not be BusStatus::Ok.
Fault fault_from(BusStatus status);

}  // namespace sms::gateway
