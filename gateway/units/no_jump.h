#pragma once
// "No jump on enable" (docs/PLC_GUIDE.md "Safety"): before a write switches a servo's torque from off to on,
// the gateway writes the hold of its goal block (position mode: goal := present position; speed
// mode: speed := 0; PWM mode: duty := 0), so a stale goal or speed left in the servo cannot make
// it move the moment the torque comes on. A servo whose torque is already on is left alone: a
// hold would cancel the move it is making. One rule for every path that switches torque on: a
// servo unit's writes (any function, staged or not: the hold itself is written at once, since
// with the torque off it moves nothing) and a sync group on the torque field.
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
  MotionEpoch epoch = 0;     // the admission of the torque-on write
  std::string label;         // "unit 1 (bus arm, servo 1)", for the log
};

// Reads every target's state, writes the holds where the torque is off, then runs `done` on the
// io thread (through `post`) with nullopt, or with the first failure (nothing after it written;
// the caller answers it and does not switch the torque on).
void hold_before_torque_on(std::vector<HoldTarget> targets, const PostFn& post,
                           const std::function<void(std::optional<BusResult>)>& done);

}  // namespace sms::gateway
