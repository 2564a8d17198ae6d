#include "gateway/bus/poll_cache.h"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace sms::gateway {

PollCache::PollCache(std::span<const ServoEntry> servos, std::uint8_t bytes_per_address)
    : bytes_per_address_(bytes_per_address), counters_(std::make_unique<ServoCounters[]>(servos.size())) {
  if (bytes_per_address != 1 && bytes_per_address != 2) {
    throw std::invalid_argument("poll cache: an address holds 1 byte (packet buses) or 2 (Modbus registers), not " +
                                std::to_string(bytes_per_address));
  }
  index_.fill(kNoServo);
  slots_.reserve(servos.size());
  for (const auto& servo : servos) {
    if (servo.servo_id >= protocol::kBroadcastId) {
      throw std::invalid_argument("poll cache: servo ID " + std::to_string(servo.servo_id) +
                                  " is not a unicast ID (0-253)");
    }
    if (index_[servo.servo_id] != kNoServo) {
      throw std::invalid_argument("poll cache: servo ID " + std::to_string(servo.servo_id) +
                                  " is configured twice on one bus");
    }
    index_[servo.servo_id] = static_cast<std::uint8_t>(slots_.size());
    Slot slot;
    slot.servo_id = servo.servo_id;
    slot.block = servo.block;
    slot.bytes.assign(std::size_t{servo.block.count} * bytes_per_address_, 0);
    slots_.push_back(std::move(slot));
  }
}

const PollCache::Slot* PollCache::slot(std::uint8_t servo_id) const {
  const auto index = index_[servo_id];
  return index == kNoServo ? nullptr : &slots_[index];
}

PollCache::Slot* PollCache::slot(std::uint8_t servo_id) {
  const auto index = index_[servo_id];
  return index == kNoServo ? nullptr : &slots_[index];
}

void PollCache::fill_state(const Slot& slot, std::size_t index, CachedServoState& state) const {
  state.servo_id = slot.servo_id;
  state.block = slot.block;
  state.online = slot.online;
  state.offline_reason = slot.offline_reason;
  state.has_data = slot.has_data;
  state.updated = slot.updated;
  state.identity = slot.identity;
  state.response_level = slot.response_level;
  state.counters = counters_[index].snapshot();
}

std::vector<std::uint8_t> PollCache::servo_ids() const {
  std::vector<std::uint8_t> ids;
  ids.reserve(slots_.size());
  for (const auto& slot : slots_) ids.push_back(slot.servo_id);
  return ids;
}

std::optional<AddressBlock> PollCache::block(std::uint8_t servo_id) const {
  const Slot* found = slot(servo_id);
  if (found == nullptr) return std::nullopt;
  return found->block;  // fixed at construction: no lock needed
}

CacheRead PollCache::copy(std::uint8_t servo_id, std::uint16_t address, std::span<std::uint8_t> out,
                          CachedServoState* state) const {
  const auto index = index_[servo_id];
  if (index == kNoServo) return CacheRead::UnknownServo;
  const Slot& found = slots_[index];
  std::lock_guard lock(mutex_);
  if (state != nullptr) fill_state(found, index, *state);
  if (out.size() % bytes_per_address_ != 0 || !found.block.contains(address, out.size() / bytes_per_address_)) {
    return CacheRead::OutsideBlock;
  }
  if (!found.has_data) return CacheRead::NoData;
  const std::size_t offset = std::size_t{address} - found.block.address;
  std::copy_n(found.bytes.begin() + static_cast<std::ptrdiff_t>(offset * bytes_per_address_), out.size(), out.begin());
  return CacheRead::Ok;
}

std::optional<CachedServoState> PollCache::state(std::uint8_t servo_id) const {
  const auto index = index_[servo_id];
  if (index == kNoServo) return std::nullopt;
  CachedServoState state;
  std::lock_guard lock(mutex_);
  fill_state(slots_[index], index, state);
  return state;
}

std::size_t PollCache::online_count() const {
  std::lock_guard lock(mutex_);
  return static_cast<std::size_t>(std::count_if(slots_.begin(), slots_.end(), [](const Slot& s) { return s.online; }));
}

std::size_t PollCache::offline_count(OfflineReason reason) const {
  std::lock_guard lock(mutex_);
  return static_cast<std::size_t>(std::count_if(
      slots_.begin(), slots_.end(), [&](const Slot& s) { return !s.online && s.offline_reason == reason; }));
}

void PollCache::store_block(std::uint8_t servo_id, std::span<const std::uint8_t> bytes, SteadyClock::time_point when) {
  Slot* found = slot(servo_id);
  if (found == nullptr || bytes.size() != found->bytes.size()) return;
  std::lock_guard lock(mutex_);
  std::copy(bytes.begin(), bytes.end(), found->bytes.begin());
  found->has_data = true;
  found->updated = when;
  found->online = true;
  found->offline_reason = OfflineReason::None;
}

void PollCache::set_online(std::uint8_t servo_id, bool online) {
  if (!online) {
    set_offline(servo_id, OfflineReason::NoAnswer);
    return;
  }
  Slot* found = slot(servo_id);
  if (found == nullptr) return;
  std::lock_guard lock(mutex_);
  found->online = true;
  found->offline_reason = OfflineReason::None;
}

OfflineReason PollCache::set_offline(std::uint8_t servo_id, OfflineReason reason) {
  Slot* found = slot(servo_id);
  if (found == nullptr) return OfflineReason::None;
  std::lock_guard lock(mutex_);
  const OfflineReason before = found->offline_reason;
  found->online = false;
  if (!(reason == OfflineReason::NoAnswer && before == OfflineReason::AnswersLate)) found->offline_reason = reason;
  return before;
}

void PollCache::set_all_offline() {
  std::lock_guard lock(mutex_);
  for (auto& slot : slots_) {
    slot.online = false;
    slot.offline_reason = OfflineReason::NoAnswer;
  }
}

void PollCache::set_identity(std::uint8_t servo_id, const ServoIdentity& identity) {
  Slot* found = slot(servo_id);
  if (found == nullptr) return;
  std::lock_guard lock(mutex_);
  found->identity = identity;
}

void PollCache::set_response_level(std::uint8_t servo_id, std::optional<std::uint8_t> level) {
  Slot* found = slot(servo_id);
  if (found == nullptr) return;
  std::lock_guard lock(mutex_);
  found->response_level = level;
}

ServoCounters* PollCache::counters(std::uint8_t servo_id) {
  const auto index = index_[servo_id];
  return index == kNoServo ? nullptr : &counters_[index];
}

const ServoCounters* PollCache::counters(std::uint8_t servo_id) const {
  const auto index = index_[servo_id];
  return index == kNoServo ? nullptr : &counters_[index];
}

}  // namespace sms::gateway
