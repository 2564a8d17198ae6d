// A bus engine's result as the Modbus exception a client is answered with (gateway/units/bus_faults).
#include <gtest/gtest.h>

#include <stdexcept>

#include "gateway/service/faults.h"
#include "gateway/units/bus_faults.h"

namespace sms::gateway {
namespace {

TEST(ModbusException, BusStatusesMapToTheirFaults) {
  EXPECT_EQ(exception_code(fault_from(BusStatus::Timeout)), 0x0B);
  EXPECT_EQ(exception_code(fault_from(BusStatus::Corrupt)), 0x04);
  EXPECT_EQ(fault_from(BusStatus::Dropped), Fault::InternalError);
  EXPECT_EQ(exception_code(fault_from(BusStatus::Dropped)), 0x04);
  EXPECT_EQ(exception_code(fault_from(BusStatus::ServoRefused)), 0x04);
  EXPECT_EQ(exception_code(fault_from(BusStatus::BusDown)), 0x0A);
  EXPECT_EQ(exception_code(fault_from(BusStatus::QueueFull)), 0x06);
  EXPECT_EQ(exception_code(fault_from(BusStatus::Cancelled)), 0x0A);
  EXPECT_THROW(fault_from(BusStatus::Ok), std::logic_error);
}

}  // namespace
}  // namespace sms::gateway
