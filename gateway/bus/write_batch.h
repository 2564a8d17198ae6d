#pragma once
// The frames of writes to several servos of one bus, as DynamixelSDK's GroupSyncWrite: on a
// packet bus every write of the same address and length shares one SYNC WRITE frame, with as
// many servos as its LEN allows (83 of a 2-byte field, 35 of a 6-byte goal block; more take
// another frame); on a modbus-rtu bus, which has no SYNC WRITE, each write is a frame of its own.
// Used by the safety stop and the gateway unit's sync groups.
#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

#include "gateway/bus/bus_operations.h"
#include "protocol/instructions.h"

namespace sms::gateway {

class WriteBatch {
 public:
  explicit WriteBatch(bool sync_write) : sync_write_(sync_write) {}

  // Adds one servo's write; returns the index of the frame it went into.
  std::size_t add(std::uint8_t servo_id, std::uint16_t address, Bytes data) {
    if (!sync_write_) {
      frames_.push_back(WriteOp{servo_id, address, std::move(data)});
      return frames_.size() - 1;
    }
    const auto length = static_cast<std::uint8_t>(data.size());
    auto frame = std::find_if(frames_.begin(), frames_.end(), [&](const BusOp& op) {
      const auto* sync = std::get_if<SyncWriteOp>(&op);
      return sync != nullptr && sync->address == address && sync->length == length &&
             sync->entries.size() < protocol::max_sync_write_servos(length);
    });
    if (frame == frames_.end()) {
      frames_.push_back(SyncWriteOp{address, length, {}});
      frame = std::prev(frames_.end());
    }
    std::get<SyncWriteOp>(*frame).entries.push_back(protocol::SyncWriteEntry{servo_id, std::move(data)});
    return static_cast<std::size_t>(frame - frames_.begin());
  }

  std::vector<BusOp>& frames() { return frames_; }

 private:
  bool sync_write_;
  std::vector<BusOp> frames_;
};

}  // namespace sms::gateway
