// What the Sparkplug node publishes between births: the node's safety state (NDATA) and each
// device's fields from the poll cache on change and every report_period (DDATA).
#include "gateway/mqtt/sparkplug_node_impl.h"

#include <cstdlib>

#include "gateway/units/gateway_unit.h"

namespace sms::gateway {

void SparkplugNode::Impl::schedule() {
  if (stopping_) return;
  timer_.expires_after(settings_.data_period);
  timer_.async_wait([weak = weak_from_this()](const boost::system::error_code& error) {
    if (auto self = weak.lock(); self && !error) self->tick();
  });
}

void SparkplugNode::Impl::tick() {
  schedule();
  if (!session_ || stopping_) return;
  read_node_state();
  const auto now = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < devices_.size(); ++i) {
    if (!devices_[i].busy) check_device(i, now);
  }
}

void SparkplugNode::Impl::read_node_state() {
  ask(config_.modbus_tcp.gateway_unit_id, ReadBitsRequest{fc::kReadCoils, gateway_unit_layout::kEStopCoil, 2},
      [this](const Answer& answer) {
        if (!answer.ok() || !session_) return;
        const bool estop = answer.bit(0), tripped = answer.bit(1);
        if (estop == estop_ && tripped == tripped_) return;
        sp::Payload payload;
        if (estop != estop_) payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kEStop), estop));
        if (tripped != tripped_) {
          payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kWatchdogTripped), tripped));
        }
        estop_ = estop;
        tripped_ = tripped;
        publish(sp::MessageType::NData, std::move(payload));
      });
  // A stop that could not be delivered yet (docs/SAFETY.md): a host must see it, not only a PLC.
  ask(config_.modbus_tcp.gateway_unit_id,
      ReadRegistersRequest{fc::kReadInputRegisters, gateway_unit_layout::kOwedStops, 1}, [this](const Answer& answer) {
        if (!answer.ok() || !session_) return;
        const auto registers = answer.registers();
        if (registers.empty() || registers[0] == stops_owed_) return;
        stops_owed_ = registers[0];
        sp::Payload payload;
        payload.metrics.push_back(sp::Metric::uint16(std::string(metric_name::kStopsOwed), stops_owed_));
        publish(sp::MessageType::NData, std::move(payload));
      });
  // The heartbeat registers (holding 1000 + n), as any client reads them: written by a PLC, a host's
  // NCMD or the console alike.
  if (!heartbeats_.empty()) {
    ask(config_.modbus_tcp.gateway_unit_id,
        ReadRegistersRequest{fc::kReadHoldingRegisters, config::kHeartbeatRegisterBase,
                             static_cast<std::uint16_t>(heartbeats_.size())},
        [this](const Answer& answer) {
          const auto registers = answer.registers();
          if (!answer.ok() || !session_ || registers.size() != heartbeat_values_.size()) return;
          sp::Payload payload;
          for (std::size_t bus = 0; bus < registers.size(); ++bus) {
            if (registers[bus] == heartbeat_values_[bus]) continue;
            heartbeat_values_[bus] = registers[bus];
            payload.metrics.push_back(sp::Metric::uint16(heartbeats_[bus], registers[bus]));
          }
          if (!payload.metrics.empty()) publish(sp::MessageType::NData, std::move(payload));
        });
  }
  // A safety state the gateway could not save (a restart would lose a latch or an owed stop).
  ask(config_.modbus_tcp.gateway_unit_id,
      ReadBitsRequest{fc::kReadDiscreteInputs, gateway_unit_layout::kStateNotPersistedInput, 1},
      [this](const Answer& answer) {
        if (!answer.ok() || !session_ || answer.bit(0) == not_persisted_) return;
        not_persisted_ = answer.bit(0);
        sp::Payload payload;
        payload.metrics.push_back(sp::Metric::boolean(std::string(metric_name::kStateNotPersisted), not_persisted_));
        publish(sp::MessageType::NData, std::move(payload));
      });
}

// Facts first (online, status, counters: FC04 1000-1007), then birth, death or data.
void SparkplugNode::Impl::check_device(std::size_t index, std::chrono::steady_clock::time_point now) {
  Device& device = devices_[index];
  device.busy = true;
  ask(device.unit_id,
      ReadRegistersRequest{fc::kReadInputRegisters, servo_facts_layout::kFirstRegister,
                           servo_facts_layout::kRegisterCount},
      [this, index, now](const Answer& answer) {
        Device& device = devices_[index];
        const auto facts = answer.registers();
        if (!answer.ok() || facts.size() < servo_facts_layout::kRegisterCount || !session_) {
          device.busy = false;
          return;
        }
        const bool online = facts[servo_facts_layout::kOnline] != 0;
        if (!online) {
          if (device.born) publish_device_death(device);
          device.busy = false;
          return;
        }
        if (!device.born) return birth(index, facts);
        data(index, facts, now);
      });
}

void SparkplugNode::Impl::data(std::size_t index, std::vector<std::uint16_t> facts,
                               std::chrono::steady_clock::time_point now) {
  Device& device = devices_[index];
  const bool report_all = settings_.report_period.count() > 0 && now - device.reported >= settings_.report_period;
  if (!device.cache_read) {
    device.busy = false;
    if (report_all || facts[servo_facts_layout::kStatus] != device.status) publish_data(device, facts, {}, report_all);
    return;
  }
  ask(device.unit_id, *device.cache_read, [this, index, facts, report_all](const Answer& answer) {
    Device& device = devices_[index];
    device.busy = false;
    if (!answer.ok() || !session_ || !device.born) return;
    const auto registers = answer.registers();
    std::vector<std::size_t> changed;
    for (std::size_t m = 0; m < device.metrics.size(); ++m) {
      auto& slot = device.metrics[m];
      if (!slot.from_cache) continue;
      const std::size_t offset = slot.entry->address - device.cache_read->address;
      if (offset >= registers.size()) continue;
      const std::int64_t value = field_value(*slot.entry, registers[offset]);
      const bool moved = !slot.value || (value != *slot.value && std::llabs(value - *slot.value) >= slot.deadband);
      if (moved || report_all) {
        slot.value = value;
        changed.push_back(m);
      }
    }
    if (!changed.empty() || facts[servo_facts_layout::kStatus] != device.status || report_all)
      publish_data(device, facts, changed, report_all);
  });
}

void SparkplugNode::Impl::publish_data(Device& device, const std::vector<std::uint16_t>& facts,
                                       const std::vector<std::size_t>& changed, bool report_all) {
  sp::Payload payload;
  const std::uint64_t acquired = acquisition_time(facts[servo_facts_layout::kCacheAge]);
  for (const auto m : changed) {
    auto metric = field_metric(device.metrics[m].name, *device.metrics[m].entry, device.metrics[m].value);
    metric.timestamp = acquired;
    payload.metrics.push_back(std::move(metric));
  }
  if (report_all) {
    for (const auto& slot : device.metrics) {
      if (!slot.from_cache) payload.metrics.push_back(field_metric(slot.name, *slot.entry, slot.value));
    }
    device.reported = std::chrono::steady_clock::now();
  }
  append_facts(payload, device, facts, report_all);
  publish(sp::MessageType::DData, std::move(payload), device.id);
}

// The poll's time from the cache age (facts register 1002, ms, 65535: unknown or older).
std::uint64_t SparkplugNode::Impl::acquisition_time(std::uint16_t age_ms) {
  const std::uint64_t now = epoch_ms();
  return age_ms == 0xFFFF ? now : now - age_ms;
}

}  // namespace sms::gateway
