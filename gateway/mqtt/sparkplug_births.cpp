// The Sparkplug node's births and deaths: NBIRTH, each servo's device (its metrics, read in as few
// requests as the map allows), DBIRTH when it is online and DDEATH when it is not.
#include "gateway/mqtt/sparkplug_node_impl.h"

#include <algorithm>

#include <spdlog/spdlog.h>

namespace sms::gateway {

std::int64_t SparkplugNode::Impl::field_value(const RegisterEntry& entry, std::uint16_t reg) {
  return entry.min < 0 ? std::int64_t{static_cast<std::int16_t>(reg)} : std::int64_t{reg};
}

sp::DataType SparkplugNode::Impl::field_type(const RegisterEntry& entry) {
  return entry.min < 0 ? sp::DataType::Int16 : sp::DataType::UInt16;
}

sp::Metric SparkplugNode::Impl::field_metric(const std::string& name, const RegisterEntry& entry,
                                             std::optional<std::int64_t> value) {
  sp::Metric metric = sp::Metric::of(name, field_type(entry), std::monostate{});
  if (!value) {
    metric.value = std::monostate{};
  } else if (field_type(entry) == sp::DataType::Int16) {
    metric.value = *value;
  } else {
    metric.value = static_cast<std::uint64_t>(*value);
  }
  return metric;
}

SparkplugNode::Impl::Device SparkplugNode::Impl::make_device(const config::ServoConfig& servo, const ServoUnit& unit) {
  Device device;
  device.unit_id = servo.unit_id;
  device.id = config::sparkplug_device_id(servo);
  device.unit = &unit;
  const auto& map = unit.map;
  std::vector<const RegisterEntry*> cached, live;
  for (const auto& entry : map.entries()) {
    if (!entry.readable && !entry.writable) continue;
    MetricSlot slot;
    slot.name = std::string(entry.shown->name);
    slot.entry = &entry;
    slot.from_cache = entry.readable && map.plan_input_read(entry.address, 1, unit.poll_block).has_value();
    for (const auto& band : settings_.deadbands) {
      if (band.field == slot.name) slot.deadband = band.deadband;
    }
    if (slot.from_cache) cached.push_back(&entry);
    if (entry.readable && !slot.from_cache) live.push_back(&entry);
    device.metrics.push_back(std::move(slot));
  }
  if (!cached.empty()) {
    const auto first = cached.front()->address;
    const auto count = static_cast<std::uint16_t>(cached.back()->address - first + 1);
    if (count <= limits::kReadRegisters && map.plan_input_read(first, count, unit.poll_block)) {
      device.cache_read = ReadRegistersRequest{fc::kReadInputRegisters, first, count};
    } else {
      for (auto& slot : device.metrics) {  // cannot be read in one: read them live instead
        if (slot.from_cache) live.push_back(slot.entry);
        slot.from_cache = false;
      }
      std::sort(live.begin(), live.end(), [](auto* a, auto* b) { return a->address < b->address; });
    }
  }
  // Runs of live fields, each one FC03 the map accepts (at most 125 registers).
  for (const modbus_map::BusRange& run : map.live_read_runs(live)) {
    device.live_reads.push_back(ReadRegistersRequest{fc::kReadHoldingRegisters, run.address, run.count});
  }
  return device;
}

void SparkplugNode::Impl::publish_node_birth() {
  sp::Payload payload;
  payload.metrics.push_back(
      sp::Metric::int64(std::string(sp::kBdSeqMetric), static_cast<std::int64_t>(bd_seq_.load())));
  payload.metrics.push_back(sp::Metric::boolean(std::string(sp::kRebirthMetric), false));
  payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kVersion), SMS_GATEWAY_VERSION));
  payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kEStop), estop_));
  payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kWatchdogTripped), tripped_));
  payload.metrics.push_back(sp::Metric::uint16(std::string(metric_name::kStopsOwed), stops_owed_));
  payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kStateNotPersisted), not_persisted_));
  // What holding 1000 + n of the gateway unit reads: the last value written, 0 before any.
  for (std::size_t bus = 0; bus < heartbeats_.size(); ++bus) {
    payload.metrics.push_back(sp::Metric::uint16(heartbeats_[bus], heartbeat_values_[bus]));
  }
  publish(sp::MessageType::NBirth, std::move(payload));
}

void SparkplugNode::Impl::birth(std::size_t index, const std::vector<std::uint16_t>& facts) {
  Device& device = devices_[index];
  std::vector<ReadRegistersRequest> reads = device.live_reads;
  if (device.cache_read) reads.insert(reads.begin(), *device.cache_read);
  read_all(device.unit_id, reads, {}, [this, index, reads, facts](std::vector<Answer> answers) {
    Device& device = devices_[index];
    device.busy = false;
    if (answers.size() != reads.size() || !answers.back().ok() || !session_) return;  // next tick again
    for (std::size_t i = 0; i < reads.size(); ++i) store(device, reads[i], answers[i].registers());
    const std::uint64_t acquired = acquisition_time(facts[servo_facts_layout::kCacheAge]);
    sp::Payload payload;
    for (const auto& slot : device.metrics) {
      auto metric = field_metric(slot.name, *slot.entry, slot.value);
      metric.eng_unit = std::string(slot.entry->shown->unit);
      metric.read_only = !slot.entry->writable;
      if (slot.from_cache) metric.timestamp = acquired;
      payload.metrics.push_back(std::move(metric));
    }
    device.status = facts[servo_facts_layout::kStatus];
    append_facts(payload, device, facts, true);
    device.born = true;
    device.reported = std::chrono::steady_clock::now();
    publish(sp::MessageType::DBirth, std::move(payload), device.id);
    set_online_count();
  });
}

void SparkplugNode::Impl::store(Device& device, const ReadRegistersRequest& read,
                                const std::vector<std::uint16_t>& registers) {
  for (auto& slot : device.metrics) {
    if (!slot.entry->readable || slot.entry->address < read.address) continue;
    const std::size_t offset = slot.entry->address - read.address;
    if (offset < registers.size() && offset < read.count) slot.value = field_value(*slot.entry, registers[offset]);
  }
}

// Status on change (and in births and full reports); the counters only in births and reports,
// since they change on every poll.
void SparkplugNode::Impl::append_facts(sp::Payload& payload, Device& device, const std::vector<std::uint16_t>& facts,
                                       bool everything) {
  if (everything || facts[servo_facts_layout::kStatus] != device.status) {
    payload.metrics.push_back(
        sp::Metric::uint16(std::string(metric_name::kStatus), facts[servo_facts_layout::kStatus]));
    device.status = facts[servo_facts_layout::kStatus];
  }
  if (everything) {
    // UInt64 (long_value) rather than UInt32: the spec puts UInt32 in int_value, Tahu's Java and
    // JS decoders read it from long_value; for UInt64 both agree (docs/DECISIONS.md).
    namespace at = servo_facts_layout;
    const auto counter = [&](std::size_t offset) { return std::uint64_t{facts[offset]} << 16 | facts[offset + 1]; };
    payload.metrics.push_back(sp::Metric::uint64(std::string(metric_name::kRepliesOk), counter(at::kRepliesOk)));
    payload.metrics.push_back(sp::Metric::uint64(std::string(metric_name::kTimeouts), counter(at::kTimeouts)));
    payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kLastCommand), device.last_command));
  }
}

void SparkplugNode::Impl::publish_device_death(Device& device) {
  device.born = false;
  publish(sp::MessageType::DDeath, sp::Payload{}, device.id);
  spdlog::info("mqtt: device {} (unit {}) is offline: DDEATH", device.id, device.unit_id);
  set_online_count();
}

void SparkplugNode::Impl::set_online_count() {
  std::size_t online = 0;
  for (const auto& device : devices_) online += device.born ? 1 : 0;
  std::lock_guard lock(stats_mutex_);
  stats_.devices_online = online;
}

}  // namespace sms::gateway
