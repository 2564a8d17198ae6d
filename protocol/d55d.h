#pragma once
// Vendor protocol with header `D5 5D`, docs/PROTOCOL.md §1.2: the instructions beyond the common set.
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>
#include <variant>
#include <vector>

#include "protocol/instructions.h"
#include "protocol/packet.h"

namespace sms::protocol::d55d {

inline constexpr std::uint8_t kReset = 0x06;
inline constexpr std::uint8_t kStartEnd = 0x07;
inline constexpr std::uint8_t kTrajectoryWrite = 0x0A;
inline constexpr std::uint8_t kTrajectoryAction = 0x0B;
inline constexpr std::uint8_t kCustom = 0xFF;

inline constexpr std::uint8_t kCustomRelativeMove = 0x01;
inline constexpr std::uint8_t kCustomAbsoluteMove = 0x02;
inline constexpr std::uint8_t kCustomChangeSpeed = 0x03;

// Every instruction of docs/PROTOCOL.md §1.2, in code order.
inline constexpr std::array<InstructionSpec, 11> kInstructions{{
    {common::kPing, "PING"},
    {common::kRead, "READ"},
    {common::kWrite, "WRITE"},
    {common::kRegWrite, "REG WRITE"},
    {common::kAction, "ACTION"},
    {kReset, "RESET"},
    {kStartEnd, "START END"},
    {kTrajectoryWrite, "TRAJECTORY WRITE"},
    {kTrajectoryAction, "TRAJECTORY ACTION"},
    {common::kSyncWrite, "SYNC WRITE"},
    {kCustom, "CUSTOM"},
}};
// Name of an instruction code, nullopt for a code d55d does not define.
std::optional<std::string_view> instruction_name(std::uint8_t code);

// TRAJECTORY WRITE carries count + 3 bytes a point within LEN's 253 parameter bytes.
inline constexpr std::size_t kMaxTrajectoryPoints = (kMaxParams - 1) / 3;

// Status ERROR bits (docs/PROTOCOL.md §1.2, doc 002 §2.3).
namespace error_bit {
inline constexpr std::uint8_t kOverTemperature = 1 << 0;
inline constexpr std::uint8_t kOverCurrent = 1 << 1;
inline constexpr std::uint8_t kOverVoltage = 1 << 2;
inline constexpr std::uint8_t kUnderVoltage = 1 << 3;
inline constexpr std::uint8_t kChecksum = 1 << 4;
inline constexpr std::uint8_t kInstruction = 1 << 5;
inline constexpr std::uint8_t kStall = 1 << 6;
}  // namespace error_bit

struct TrajectoryPoint {
  std::uint16_t angle = 0;  // degrees x resolution, as goal position
  std::uint8_t speed = 0;
  friend bool operator==(const TrajectoryPoint&, const TrajectoryPoint&) = default;
};

// Speeds in custom moves: bit 15 is the direction (sign-magnitude), as the run speed field.
struct RelativeMove {
  std::uint16_t relative = 0;
  std::uint16_t speed = 0;
  std::optional<std::uint8_t> acceleration;  // the 6-byte form carries accel and decel
  std::optional<std::uint8_t> deceleration;
  friend bool operator==(const RelativeMove&, const RelativeMove&) = default;
};
struct AbsoluteMove {
  std::uint16_t position = 0;
  std::uint16_t speed = 0;
  std::uint8_t acceleration = 0;
  std::uint8_t deceleration = 0;
  friend bool operator==(const AbsoluteMove&, const AbsoluteMove&) = default;
};
struct ChangeSpeed {
  std::uint16_t speed = 0;
  friend bool operator==(const ChangeSpeed&, const ChangeSpeed&) = default;
};
using CustomMove = std::variant<RelativeMove, AbsoluteMove, ChangeSpeed>;

Packet reset(std::uint8_t id);
// The document does not give START END's parameters; they are passed through as given.
Packet start_end(std::uint8_t id, std::span<const std::uint8_t> params);
// Throws std::invalid_argument for no points, std::length_error past kMaxTrajectoryPoints.
Packet trajectory_write(std::uint8_t id, std::span<const TrajectoryPoint> points);
Packet trajectory_action(std::uint8_t id);
// Throws std::invalid_argument for a RelativeMove with only one of accel/decel.
Packet custom(std::uint8_t id, const CustomMove& move);

// Malformed: count 0, or a count that disagrees with the number of 3-byte points.
std::optional<std::vector<TrajectoryPoint>> parse_trajectory_write(std::span<const std::uint8_t> params);
// Decision (docs/PROTOCOL.md §1.2): sub 0x01 is decoded by length, 4 bytes or 6 with accel/decel.
std::optional<CustomMove> parse_custom(std::span<const std::uint8_t> params);
// The PING reply may carry LEN 2 or 3 (docs/PROTOCOL.md §1.2 decision); both are accepted.

}  // namespace sms::protocol::d55d
