#pragma once
// Instruction builders and parsers. The common instructions (PING, READ, WRITE, REG WRITE,
// ACTION, SYNC WRITE) have the same code and parameter layout in both packet protocols,
// so they are built once here; protocol-specific ones live in feetech.h and d55d.h.
// Builders return a Packet; encode(format, packet) frames it. Parsers take the params of
// a decoded request and return nullopt when they are malformed (the simulator answers
// those with the protocol's instruction-error bit).
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "protocol/packet.h"

namespace sms::protocol {

// Codes shared by feetech and d55d.
namespace common {
inline constexpr std::uint8_t kPing = 0x01;
inline constexpr std::uint8_t kRead = 0x02;
inline constexpr std::uint8_t kWrite = 0x03;
inline constexpr std::uint8_t kRegWrite = 0x04;
inline constexpr std::uint8_t kAction = 0x05;
inline constexpr std::uint8_t kSyncWrite = 0x83;
}  // namespace common

// One row of a protocol's instruction table (feetech::kInstructions, d55d::kInstructions).
struct InstructionSpec {
  std::uint8_t code = 0;
  std::string_view name;  // as docs/PROTOCOL.md §1.1 / §1.2 spell it, for logs
};

Packet ping(std::uint8_t id);
Packet read(std::uint8_t id, std::uint8_t address, std::uint8_t count);
Packet write(std::uint8_t id, std::uint8_t address, std::span<const std::uint8_t> data);
Packet reg_write(std::uint8_t id, std::uint8_t address, std::span<const std::uint8_t> data);
Packet action(std::uint8_t id = kBroadcastId);
// A status reply: `error` is the servo's ERROR byte, `params` the data it returns.
Packet status(std::uint8_t id, std::uint8_t error, std::span<const std::uint8_t> params = {});

struct SyncWriteEntry {
  std::uint8_t id = 0;
  Bytes data;  // exactly `length` bytes
  friend bool operator==(const SyncWriteEntry&, const SyncWriteEntry&) = default;
};
// Broadcast frame: addr, L, (id, L bytes)...; throws std::invalid_argument when an entry's
// size differs from `length`, std::length_error when the frame would not fit LEN.
Packet sync_write(std::uint8_t address, std::uint8_t length, std::span<const SyncWriteEntry> entries);
// How many servos one SYNC WRITE of `length` data bytes each can carry: 2 + n x (1 + length)
// parameter bytes within LEN's limit (35 servos for a 6-byte block, 83 for one 2-byte field).
constexpr std::size_t max_sync_write_servos(std::uint8_t length) { return (kMaxParams - 2) / (1U + length); }

struct ReadRequest {
  std::uint8_t address = 0;
  std::uint8_t count = 0;
};
struct WriteRequest {  // WRITE and REG WRITE
  std::uint8_t address = 0;
  Bytes data;
};
struct SyncWriteRequest {
  std::uint8_t address = 0;
  std::uint8_t length = 0;
  std::vector<SyncWriteEntry> entries;
};

// Malformed: a READ without exactly addr and a non-zero count; a WRITE without at least one
// data byte; a SYNC WRITE whose entries do not each hold id + L bytes, or that has none.
std::optional<ReadRequest> parse_read(std::span<const std::uint8_t> params);
std::optional<WriteRequest> parse_write(std::span<const std::uint8_t> params);
std::optional<SyncWriteRequest> parse_sync_write(std::span<const std::uint8_t> params);

}  // namespace sms::protocol
