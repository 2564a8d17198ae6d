#include "protocol/feetech.h"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace sms::protocol::feetech {

static_assert(std::is_sorted(kInstructions.begin(), kInstructions.end(),
                             [](const InstructionSpec& a, const InstructionSpec& b) { return a.code < b.code; }),
              "feetech::kInstructions must stay in code order");

std::optional<std::string_view> instruction_name(std::uint8_t code) {
  const auto* it = std::find_if(kInstructions.begin(), kInstructions.end(),
                                [code](const InstructionSpec& spec) { return spec.code == code; });
  if (it == kInstructions.end()) return std::nullopt;
  return it->name;
}

Packet recovery(std::uint8_t id) { return Packet{id, kRecovery, {}}; }
Packet reboot(std::uint8_t id) { return Packet{id, kReboot, {}}; }
Packet backup(std::uint8_t id) { return Packet{id, kBackup, {}}; }
Packet reset_status(std::uint8_t id) { return Packet{id, kResetStatus, {}}; }

Packet calibrate(std::uint8_t id, std::optional<std::uint16_t> position) {
  Packet packet{id, kCalibrate, {}};
  if (position) {
    packet.params = {static_cast<std::uint8_t>(*position & 0xFF), static_cast<std::uint8_t>(*position >> 8)};
  }
  return packet;
}

Packet sync_read(std::uint8_t address, std::uint8_t count, std::span<const std::uint8_t> ids) {
  if (ids.empty() || count == 0) {
    throw std::invalid_argument("SYNC READ at address " + std::to_string(address) + " needs a count > 0 and at " +
                                "least one servo (got count " + std::to_string(count) + ", " +
                                std::to_string(ids.size()) + " servos)");
  }
  if (2 + ids.size() > kMaxParams) {
    throw std::length_error("SYNC READ of " + std::to_string(ids.size()) + " servos: LEN allows at most " +
                            std::to_string(kMaxParams - 2) + "; split it");
  }
  Packet packet{kBroadcastId, kSyncRead, {}};
  packet.params.reserve(2 + ids.size());  // reserve first: GCC 12 -O2 misreads an insert after {a, b}
  packet.params.push_back(address);
  packet.params.push_back(count);
  packet.params.insert(packet.params.end(), ids.begin(), ids.end());
  return packet;
}

std::optional<SyncReadRequest> parse_sync_read(std::span<const std::uint8_t> params) {
  if (params.size() < 3 || params[1] == 0) return std::nullopt;
  return SyncReadRequest{params[0], params[1], std::vector<std::uint8_t>(params.begin() + 2, params.end())};
}

std::optional<std::optional<std::uint16_t>> parse_calibrate(std::span<const std::uint8_t> params) {
  using Position = std::optional<std::uint16_t>;
  if (params.empty()) return std::optional<Position>(std::in_place, std::nullopt);
  if (params.size() != 2) return std::nullopt;
  return std::optional<Position>(std::in_place, static_cast<std::uint16_t>(params[0] | (params[1] << 8)));
}

}  // namespace sms::protocol::feetech
