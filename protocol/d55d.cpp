#include "protocol/d55d.h"

#include <algorithm>
#include <stdexcept>
#include <string>

#include "protocol/overloaded.h"

namespace sms::protocol::d55d {
namespace {

static_assert(std::is_sorted(kInstructions.begin(), kInstructions.end(),
                             [](const InstructionSpec& a, const InstructionSpec& b) { return a.code < b.code; }),
              "d55d::kInstructions must stay in code order");

// Parameter bytes after the sub-command byte that each CUSTOM sub-command accepts (docs/PROTOCOL.md §1.2).
struct CustomLayout {
  std::uint8_t sub = 0;
  std::array<std::size_t, 2> sizes{};  // the same size twice when there is only one form
};
constexpr std::array<CustomLayout, 3> kCustomLayouts{{
    {kCustomRelativeMove, {4, 6}},  // Decision (docs/PROTOCOL.md §1.2): 6 = with accel/decel
    {kCustomAbsoluteMove, {6, 6}},
    {kCustomChangeSpeed, {2, 2}},
}};

void append_little_endian(Bytes& out, std::uint16_t value) {
  out.push_back(static_cast<std::uint8_t>(value & 0xFF));
  out.push_back(static_cast<std::uint8_t>(value >> 8));
}

std::uint16_t little_endian_at(std::span<const std::uint8_t> bytes, std::size_t offset) {
  return static_cast<std::uint16_t>(bytes[offset] | (bytes[offset + 1] << 8));
}

}  // namespace

std::optional<std::string_view> instruction_name(std::uint8_t code) {
  const auto* it = std::find_if(kInstructions.begin(), kInstructions.end(),
                                [code](const InstructionSpec& spec) { return spec.code == code; });
  if (it == kInstructions.end()) return std::nullopt;
  return it->name;
}

Packet reset(std::uint8_t id) { return Packet{id, kReset, {}}; }

Packet start_end(std::uint8_t id, std::span<const std::uint8_t> params) {
  return Packet{id, kStartEnd, Bytes(params.begin(), params.end())};
}

Packet trajectory_write(std::uint8_t id, std::span<const TrajectoryPoint> points) {
  if (points.empty()) {
    throw std::invalid_argument("TRAJECTORY WRITE to servo " + std::to_string(id) + " needs at least one point");
  }
  if (points.size() > kMaxTrajectoryPoints) {
    throw std::length_error("TRAJECTORY WRITE to servo " + std::to_string(id) + ": " + std::to_string(points.size()) +
                            " points, LEN allows at most " + std::to_string(kMaxTrajectoryPoints));
  }
  Packet packet{id, kTrajectoryWrite, {}};
  packet.params.reserve(1 + 3 * points.size());
  packet.params.push_back(static_cast<std::uint8_t>(points.size()));
  for (const auto& point : points) {
    append_little_endian(packet.params, point.angle);
    packet.params.push_back(point.speed);
  }
  return packet;
}

Packet trajectory_action(std::uint8_t id) { return Packet{id, kTrajectoryAction, {}}; }

Packet custom(std::uint8_t id, const CustomMove& move) {
  Packet packet{id, kCustom, {}};
  Bytes& params = packet.params;
  std::visit(Overloaded{
                 [&](const RelativeMove& relative) {
                   if (relative.acceleration.has_value() != relative.deceleration.has_value()) {
                     throw std::invalid_argument("CUSTOM relative move to servo " + std::to_string(id) +
                                                 ": give both acceleration and deceleration, or neither");
                   }
                   params.push_back(kCustomRelativeMove);
                   append_little_endian(params, relative.relative);
                   append_little_endian(params, relative.speed);
                   if (relative.acceleration) {
                     params.push_back(*relative.acceleration);
                     params.push_back(*relative.deceleration);
                   }
                 },
                 [&](const AbsoluteMove& absolute) {
                   params.push_back(kCustomAbsoluteMove);
                   append_little_endian(params, absolute.position);
                   append_little_endian(params, absolute.speed);
                   params.push_back(absolute.acceleration);
                   params.push_back(absolute.deceleration);
                 },
                 [&](const ChangeSpeed& change) {
                   params.push_back(kCustomChangeSpeed);
                   append_little_endian(params, change.speed);
                 },
             },
             move);
  return packet;
}

std::optional<std::vector<TrajectoryPoint>> parse_trajectory_write(std::span<const std::uint8_t> params) {
  if (params.empty() || params[0] == 0 || params.size() != 1 + 3 * std::size_t{params[0]}) return std::nullopt;
  std::vector<TrajectoryPoint> points;
  points.reserve(params[0]);
  for (std::size_t offset = 1; offset < params.size(); offset += 3) {
    points.push_back(TrajectoryPoint{little_endian_at(params, offset), params[offset + 2]});
  }
  return points;
}

std::optional<CustomMove> parse_custom(std::span<const std::uint8_t> params) {
  if (params.empty()) return std::nullopt;
  const std::uint8_t sub = params[0];
  const auto body = params.subspan(1);
  const auto* layout = std::find_if(kCustomLayouts.begin(), kCustomLayouts.end(),
                                    [sub](const CustomLayout& candidate) { return candidate.sub == sub; });
  if (layout == kCustomLayouts.end() ||
      std::find(layout->sizes.begin(), layout->sizes.end(), body.size()) == layout->sizes.end()) {
    return std::nullopt;
  }
  switch (sub) {
    case kCustomRelativeMove: {
      RelativeMove move{little_endian_at(body, 0), little_endian_at(body, 2), std::nullopt, std::nullopt};
      if (body.size() == 6) {
        move.acceleration = body[4];
        move.deceleration = body[5];
      }
      return move;
    }
    case kCustomAbsoluteMove:
      return AbsoluteMove{little_endian_at(body, 0), little_endian_at(body, 2), body[4], body[5]};
    default:  // kCustomChangeSpeed: the layout table admits no other sub-command
      return ChangeSpeed{little_endian_at(body, 0)};
  }
}

}  // namespace sms::protocol::d55d
