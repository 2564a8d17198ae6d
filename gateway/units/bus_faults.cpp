#include "gateway/units/bus_faults.h"

#include <array>
#include <stdexcept>

namespace sms::gateway {
namespace {

struct BusStatusFault {
  BusStatus status;
  Fault fault;
};
constexpr std::array kBusStatusFaults{
    BusStatusFault{BusStatus::Timeout, Fault::ServoTimeout},
    BusStatusFault{BusStatus::Corrupt, Fault::ServoCorrupt},
    BusStatusFault{BusStatus::ServoRefused, Fault::ServoRefused},
    BusStatusFault{BusStatus::BusDown, Fault::BusDown},
    BusStatusFault{BusStatus::QueueFull, Fault::QueueFull},
    BusStatusFault{BusStatus::Cancelled, Fault::GatewayStopping},
    BusStatusFault{BusStatus::Dropped, Fault::InternalError},
    BusStatusFault{BusStatus::MotionBlocked, Fault::MotionBlocked},
};

}  // namespace

Fault fault_from(BusStatus status) {
  for (const auto& entry : kBusStatusFaults) {
    if (entry.status == status) return entry.fault;
  }
  throw std::logic_error("fault_from(BusStatus::Ok): a successful bus operation is not a fault");
}

}  // namespace sms::gateway
