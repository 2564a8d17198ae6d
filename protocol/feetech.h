#pragma once
// Feetech `FF FF` protocol (SCS/STS/SMS), docs/PROTOCOL.md §1.1: the instructions beyond the common set.
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "protocol/instructions.h"
#include "protocol/packet.h"

namespace sms::protocol::feetech {

inline constexpr std::uint8_t kRecovery = 0x06;
inline constexpr std::uint8_t kReboot = 0x08;
inline constexpr std::uint8_t kBackup = 0x09;
inline constexpr std::uint8_t kResetStatus = 0x0A;
inline constexpr std::uint8_t kCalibrate = 0x0B;
inline constexpr std::uint8_t kSyncRead = 0x82;

// Every instruction of docs/PROTOCOL.md §1.1, in code order.
inline constexpr std::array<InstructionSpec, 12> kInstructions{{
    {common::kPing, "PING"},
    {common::kRead, "READ"},
    {common::kWrite, "WRITE"},
    {common::kRegWrite, "REG WRITE"},
    {common::kAction, "ACTION"},
    {kRecovery, "RECOVERY"},
    {kReboot, "REBOOT"},
    {kBackup, "BACKUP"},
    {kResetStatus, "RESET STATUS"},
    {kCalibrate, "CALIBRATE"},
    {kSyncRead, "SYNC READ"},
    {common::kSyncWrite, "SYNC WRITE"},
}};
// Name of an instruction code, nullopt for a code feetech does not define.
std::optional<std::string_view> instruction_name(std::uint8_t code);

// Status ERROR bits of the sts/sms tables (docs/PROTOCOL.md §1.1).
namespace error_bit {
inline constexpr std::uint8_t kVoltage = 1 << 0;
inline constexpr std::uint8_t kAngleSensor = 1 << 1;
inline constexpr std::uint8_t kTemperature = 1 << 2;
inline constexpr std::uint8_t kCurrent = 1 << 3;
inline constexpr std::uint8_t kAngle = 1 << 4;  // also reported for an instruction out of range
inline constexpr std::uint8_t kOverload = 1 << 5;
}  // namespace error_bit

Packet recovery(std::uint8_t id);
Packet reboot(std::uint8_t id);
Packet backup(std::uint8_t id);
Packet reset_status(std::uint8_t id);
// Without a position the present position becomes 2048; with one it becomes that value
// (two bytes, low first as STS firmware reads them).
Packet calibrate(std::uint8_t id, std::optional<std::uint16_t> position = std::nullopt);
// Broadcast; each listed servo answers in list order. Throws std::invalid_argument for no ids
// or count 0, std::length_error past 251 ids (LEN).
Packet sync_read(std::uint8_t address, std::uint8_t count, std::span<const std::uint8_t> ids);

struct SyncReadRequest {
  std::uint8_t address = 0;
  std::uint8_t count = 0;
  std::vector<std::uint8_t> ids;
};
// Malformed: fewer than addr, count and one id, or count 0.
std::optional<SyncReadRequest> parse_sync_read(std::span<const std::uint8_t> params);
// nullopt for malformed params; an engaged optional holding nullopt means "no position given".
std::optional<std::optional<std::uint16_t>> parse_calibrate(std::span<const std::uint8_t> params);

}  // namespace sms::protocol::feetech
