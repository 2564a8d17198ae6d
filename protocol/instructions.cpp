#include "protocol/instructions.h"

#include <stdexcept>
#include <string>

namespace sms::protocol {
namespace {

Packet address_and_data(std::uint8_t id, std::uint8_t code, std::uint8_t address, std::span<const std::uint8_t> data) {
  Packet packet{id, code, {}};
  packet.params.reserve(1 + data.size());
  packet.params.push_back(address);
  packet.params.insert(packet.params.end(), data.begin(), data.end());
  return packet;
}

}  // namespace

Packet ping(std::uint8_t id) { return Packet{id, common::kPing, {}}; }

Packet read(std::uint8_t id, std::uint8_t address, std::uint8_t count) {
  return Packet{id, common::kRead, {address, count}};
}

Packet write(std::uint8_t id, std::uint8_t address, std::span<const std::uint8_t> data) {
  return address_and_data(id, common::kWrite, address, data);
}

Packet reg_write(std::uint8_t id, std::uint8_t address, std::span<const std::uint8_t> data) {
  return address_and_data(id, common::kRegWrite, address, data);
}

Packet action(std::uint8_t id) { return Packet{id, common::kAction, {}}; }

Packet status(std::uint8_t id, std::uint8_t error, std::span<const std::uint8_t> params) {
  return Packet{id, error, Bytes(params.begin(), params.end())};
}

Packet sync_write(std::uint8_t address, std::uint8_t length, std::span<const SyncWriteEntry> entries) {
  if (length == 0 || entries.empty()) {
    throw std::invalid_argument("SYNC WRITE at address " + std::to_string(address) + " needs a data length > 0 and " +
                                "at least one servo (got length " + std::to_string(length) + ", " +
                                std::to_string(entries.size()) + " servos)");
  }
  const std::size_t param_count = 2 + entries.size() * (1U + length);
  if (param_count > kMaxParams) {
    throw std::length_error("SYNC WRITE of " + std::to_string(length) + " bytes to " + std::to_string(entries.size()) +
                            " servos needs " + std::to_string(param_count) + " parameter bytes, LEN allows " +
                            std::to_string(kMaxParams) + "; split it");
  }
  Packet packet{kBroadcastId, common::kSyncWrite, {}};
  packet.params.reserve(param_count);
  packet.params.push_back(address);
  packet.params.push_back(length);
  for (const auto& entry : entries) {
    if (entry.data.size() != length) {
      throw std::invalid_argument("SYNC WRITE at address " + std::to_string(address) + ": servo " +
                                  std::to_string(entry.id) + " has " + std::to_string(entry.data.size()) +
                                  " data bytes, every servo needs exactly " + std::to_string(length));
    }
    packet.params.push_back(entry.id);
    packet.params.insert(packet.params.end(), entry.data.begin(), entry.data.end());
  }
  return packet;
}

std::optional<ReadRequest> parse_read(std::span<const std::uint8_t> params) {
  if (params.size() != 2 || params[1] == 0) return std::nullopt;
  return ReadRequest{params[0], params[1]};
}

std::optional<WriteRequest> parse_write(std::span<const std::uint8_t> params) {
  if (params.size() < 2) return std::nullopt;
  return WriteRequest{params[0], Bytes(params.begin() + 1, params.end())};
}

std::optional<SyncWriteRequest> parse_sync_write(std::span<const std::uint8_t> params) {
  if (params.size() < 2) return std::nullopt;
  const std::uint8_t length = params[1];
  const auto entries = params.subspan(2);
  const std::size_t entry_size = 1U + length;
  if (length == 0 || entries.empty() || entries.size() % entry_size != 0) return std::nullopt;
  SyncWriteRequest request{params[0], length, {}};
  request.entries.reserve(entries.size() / entry_size);
  for (std::size_t offset = 0; offset < entries.size(); offset += entry_size) {
    const auto entry = entries.subspan(offset, entry_size);
    request.entries.push_back(SyncWriteEntry{entry[0], Bytes(entry.begin() + 1, entry.end())});
  }
  return request;
}

}  // namespace sms::protocol
