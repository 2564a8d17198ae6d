#pragma once
// "No jump on enable" (docs/PLC_GUIDE.md "Safety"): before a write enables a servo's motion — an
// enable field of its table (modbus_map MotionSpec::enables: the torque switch 1; d55d sleep 0,
// brake 0) given its enabling value where the servo held another, or a drive change (mode field,
// d55d/scs angle limits) of an enabled servo — the gateway writes the hold of its goal block
// (position mode: goal := present position; speed mode: speed := 0; PWM mode: duty := 0; a drive
// change: all three), so a stale goal or speed left in the servo cannot make it move the moment
// it may. An enabled servo that keeps its drive is left alone: a hold would cancel the move it is
// making. What to hold is modbus_map::plan_enable_hold's decision, from the servo's state read
// here. One rule for every path: a servo unit's writes (any function, staged or not: the hold
// itself is written at once, since a disabled servo moves nothing) and the sync groups.
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "gateway/bus/bus_join.h"
#include "modbus_map/motion.h"

namespace sms::gateway {

struct HoldTarget {
  BusEngine* engine = nullptr;
  std::uint8_t servo_id = 0;
  const modbus_map::MotionSpec* spec = nullptr;
  modbus_map::ByteOrder order = modbus_map::ByteOrder::LowFirst;
  bool expect_reply = true;  // the servo answers writes (its response level)
  MotionEpoch epoch = 0;     // the admission of the enabling write
  std::string label;         // "unit 1 (bus arm, servo 1)", for the log
  // What the request writes to this servo (bus addresses and bytes), to tell what it enables.
  std::vector<modbus_map::BusWrite> writes;
};

// Reads every target's state, writes the holds its write needs, then runs `done` on the io
// thread (through `post`) with nullopt, or with the first failure (nothing after it written;
// the caller answers it and does not write the request).
void hold_before_enable(std::vector<HoldTarget> targets, const PostFn& post,
                        const std::function<void(std::optional<BusResult>)>& done);

}  // namespace sms::gateway
