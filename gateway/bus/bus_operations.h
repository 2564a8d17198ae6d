#pragma once
// The seam between the Modbus TCP side and the servo buses. The TCP side turns Modbus
// requests into BusOps (via modbus_map's register plans) and submits them; a BusEngine
// runs them strictly one at a time on its own thread, in priority order and, within a
// priority, in submission order (so writes from one connection keep their order).
// Completion callbacks run on the bus thread: post to your own executor from there.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "protocol/instructions.h"
#include "protocol/packet.h"

namespace sms::gateway {

using protocol::Bytes;

// Lower value runs first (docs/PLC_GUIDE.md: client writes, then client live reads, then polling).
// Safety (the gateway's own safe stops, docs/PLC_GUIDE.md "Safety") goes before everything and is not
// bounded by the queue depth: a full queue must not keep a motor from stopping.
enum class Priority : std::uint8_t { Safety = 0, ClientWrite = 1, ClientRead = 2, Poll = 3 };
inline constexpr std::size_t kPriorityCount = 4;

// A write that can set a motor moving carries the safety epoch of its bus at the time the
// gateway admitted it (gateway/units/safety.h MotionGate); the engine refuses it (ServoRefused) when a
// trip or the e-stop has changed the epoch since, so nothing queued before a stop runs after it.
// 0: not a motion write.
using MotionEpoch = std::uint64_t;

// Addresses are bus addresses: bytes on packet buses, registers on modbus-rtu buses
// (where `data` holds registers high byte first).
struct ReadOp {
  std::uint8_t servo_id = 0;
  std::uint16_t address = 0;
  std::uint16_t count = 0;  // bytes (packet) or registers (modbus-rtu)
};
struct WriteOp {
  std::uint8_t servo_id = 0;
  std::uint16_t address = 0;
  Bytes data;
  bool staged = false;       // REG WRITE (packet protocols): runs on ACTION
  bool expect_reply = true;  // false when the servo's response level says it does not answer writes
  MotionEpoch motion_epoch = 0;
};
struct ActionOp {  // broadcast ACTION: runs every staged write on the bus
  MotionEpoch motion_epoch = 0;
};
struct SyncWriteOp {  // one broadcast SYNC WRITE frame, no reply
  std::uint16_t address = 0;
  std::uint8_t length = 0;
  std::vector<protocol::SyncWriteEntry> entries;
  MotionEpoch motion_epoch = 0;
};
struct PingOp {
  std::uint8_t servo_id = 0;
};
// One SYNC READ frame (feetech tables that have it): each listed servo answers in turn. Its
// BusResult's data holds, for each of `ids` in order, 1 byte (1: answered, 0: silent) and then
// `count` bytes (zeros for a silent servo): sync_read_answers() takes it apart.
struct SyncReadOp {
  std::uint16_t address = 0;
  std::uint16_t count = 0;  // bytes per servo
  std::vector<std::uint8_t> ids;
};
struct RawPduOp {          // modbus-rtu passthrough: forward a PDU as it is
  std::uint8_t slave = 0;  // 0 = broadcast, no reply awaited
  Bytes pdu;
  MotionEpoch motion_epoch = 0;
};
using BusOp = std::variant<ReadOp, WriteOp, ActionOp, SyncWriteOp, PingOp, RawPduOp, SyncReadOp>;

// The op's motion epoch; 0 for reads and pings.
MotionEpoch motion_epoch_of(const BusOp& op);

enum class BusStatus : std::uint8_t {
  Ok,
  Timeout,       // no (valid) answer after every retry -> Modbus 0x0B
  Corrupt,       // answers stayed corrupt through every retry -> 0x04
  ServoRefused,  // the servo's ERROR byte / exception says it refused -> 0x04
  BusDown,       // port missing or closed -> 0x0A
  QueueFull,     // bounded queue full: back-pressure -> 0x06
  Cancelled,     // engine stopping
  Dropped,       // the gateway could not express the operation (a defect): it never reached the bus -> 0x04
  // The safety rules' gate at the wire: a trip or the e-stop overtook a queued motion write, or
  // its servo still owes a safe stop; it never reached the bus -> 0x04 (as on the io thread).
  MotionBlocked,
};
std::string_view to_string(BusStatus status);

struct BusResult {
  BusStatus status = BusStatus::Ok;
  std::uint8_t servo_error = 0;  // status/ERROR byte of the reply (packet protocols)
  Bytes data;                    // READ payload (bytes, or registers high byte first); raw reply PDU for RawPduOp
  std::string detail;            // human context for logs: what failed, where
};

using Completion = std::function<void(BusResult)>;

// A SyncReadOp's answers by servo, in the order of its ids; nullopt where a servo was silent.
inline std::vector<std::optional<Bytes>> sync_read_answers(const SyncReadOp& op, const BusResult& result) {
  std::vector<std::optional<Bytes>> answers(op.ids.size());
  if (result.status != BusStatus::Ok) return answers;
  const std::size_t stride = 1u + op.count;
  for (std::size_t i = 0; i < op.ids.size() && (i + 1) * stride <= result.data.size(); ++i) {
    const auto at = result.data.begin() + static_cast<std::ptrdiff_t>(i * stride);
    if (*at == 1) answers[i] = Bytes(at + 1, at + static_cast<std::ptrdiff_t>(stride));
  }
  return answers;
}

}  // namespace sms::gateway
