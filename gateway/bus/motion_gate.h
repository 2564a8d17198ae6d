#pragma once
// The safety rules' hold on one bus's motion writes (docs/PLC_GUIDE.md "Safety"), shared by the safety
// supervisor (io thread), which blocks and unblocks it, and the bus engine (bus thread), which
// checks every motion write just before it goes on the wire.
//
// A trip or an e-stop blocks the gate and starts a new epoch: motion writes are refused at the
// Modbus side while blocked, and a motion write admitted before the stop (still queued on the
// bus) carries the old epoch, so the engine refuses it instead of moving a stopped motor.
#include <atomic>
#include <cstdint>

#include "gateway/bus/bus_operations.h"

namespace sms::gateway {

class MotionGate {
 public:
  // The epoch a motion write admitted now carries.
  MotionEpoch epoch() const { return epoch_.load(std::memory_order_acquire); }
  bool blocked() const { return blocked_.load(std::memory_order_acquire); }
  // Whether a motion write admitted in `admitted` may go on the wire now.
  bool admits(MotionEpoch admitted) const { return !blocked() && admitted == epoch(); }

  // The safety supervisor computes `blocked` from its whole state after every transition, under
  // its lock (gateway/units/safety_latch.cpp), so what a client reads never disagrees with the gate.
  // Blocking starts a new epoch (a motion write admitted before it is refused at the wire).
  void set_blocked(bool blocked) {
    if (blocked) {
      blocked_.store(true, std::memory_order_release);
      epoch_.fetch_add(1, std::memory_order_acq_rel);
    } else {
      blocked_.store(false, std::memory_order_release);
    }
  }

 private:
  std::atomic<MotionEpoch> epoch_{1};
  std::atomic<bool> blocked_{false};
};

}  // namespace sms::gateway
