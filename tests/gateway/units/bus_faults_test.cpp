// A bus engine's result as the Modbus exception a client is answered with (gateway/units/bus_faults).
#include <gtest/gtest.h>

#include <stdexcept>

#include "gateway/units/bus_faults.h"

namespace sms::gateway {
namespace {

using modbus_map::ModbusException;

TEST(ModbusException, BusStatusesMapToTheirExceptions) {
  EXPECT_EQ(fault_from(BusStatus::Timeout), ModbusException::GatewayTargetFailedToRespond);  // 0x0B
  EXPECT_EQ(fault_from(BusStatus::Corrupt), ModbusException::ServerDeviceFailure);           // 0x04
  EXPECT_EQ(fault_from(BusStatus::Dropped), ModbusException::ServerDeviceFailure);
  EXPECT_EQ(fault_from(BusStatus::ServoRefused), ModbusException::ServerDeviceFailure);
  EXPECT_EQ(fault_from(BusStatus::MotionBlocked), ModbusException::ServerDeviceFailure);
  EXPECT_EQ(fault_from(BusStatus::BusDown), ModbusException::GatewayPathUnavailable);  // 0x0A
  EXPECT_EQ(fault_from(BusStatus::QueueFull), ModbusException::ServerDeviceBusy);      // 0x06
  EXPECT_EQ(fault_from(BusStatus::Cancelled), ModbusException::GatewayPathUnavailable);
  EXPECT_THROW(fault_from(BusStatus::Ok), std::logic_error);
}

}  // namespace
}  // namespace sms::gateway
