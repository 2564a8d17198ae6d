// NCMD and DCMD: a command's value checked (its metric's kind and datatype, then the value check
// every way in shares), the write through the role gate and the router, its read-back, and the
// device's Gateway/Last Command.
#include "gateway/mqtt/sparkplug_node_impl.h"

#include <algorithm>

#include <spdlog/spdlog.h>

#include "gateway/units/gateway_unit.h"

namespace sms::gateway {

namespace {

// Commands waiting behind the one being carried out; past it a command is refused.
constexpr std::size_t kMaxQueuedCommands = 1024;

// What a command metric carried, for refusals: `Boolean true`, `Float 2.5`, `String "fast"`.
std::string sent(const sp::Metric& metric) {
  const std::string type(sp::to_string(metric.type));
  return std::visit(
      [&](const auto& value) -> std::string {
        using T = std::decay_t<decltype(value)>;
        if constexpr (std::is_same_v<T, std::monostate>) {
          return type + " null";
        } else if constexpr (std::is_same_v<T, bool>) {
          return type + (value ? " true" : " false");
        } else if constexpr (std::is_same_v<T, std::string>) {
          return type + " \"" + value.substr(0, 40) + "\"";
        } else {
          return type + " " + fmt::format("{}", value);
        }
      },
      metric.value);
}

}  // namespace

Expected<std::int64_t> command_value(const sp::Metric& metric, sp::DataType born_as) {
  const std::string born = std::string(sp::to_string(born_as));
  if (born_as == sp::DataType::Boolean) {
    if (const auto* flag = std::get_if<bool>(&metric.value); flag && metric.type == sp::DataType::Boolean) {
      return std::int64_t{*flag ? 1 : 0};
    }
    return unexpected("got " + sent(metric) + ", the metric is Boolean (send true or false)");
  }
  const auto range = sp::integer_range(born_as);
  const auto value = sp::integer_value(metric.value);
  const bool integer =
      std::holds_alternative<std::int64_t>(metric.value) || std::holds_alternative<std::uint64_t>(metric.value);
  if (!range || !sp::integer_range(metric.type) || !integer || !value) {
    return unexpected("got " + sent(metric) + ", the metric is " + born + " (send a whole number, datatype " + born +
                      " as in the birth)");
  }
  if (*value < range->min || *value > range->max) {
    return unexpected(std::to_string(*value) + " does not fit " + born + " (" + std::to_string(range->min) + ".." +
                      std::to_string(range->max) + "), the metric's datatype in its birth");
  }
  return *value;
}

Expected<std::uint16_t> device_command_value(const sp::Metric& metric, const modbus_map::RegisterMap& map,
                                             const RegisterEntry& entry) {
  const auto value = command_value(metric, SparkplugNode::Impl::field_type(entry));
  if (!value) return unexpected(value.error());
  const auto checked = map.check_write(entry, *value);
  if (!checked) return unexpected(modbus_map::to_string(checked.error()));
  return checked->register_value;
}
void SparkplugNode::Impl::on_message(const std::string& topic_text, const Bytes& bytes) {
  if (!settings_.primary_host_id.empty() && topic_text == sp::state_topic(settings_.primary_host_id)) {
    return on_host_state(bytes);
  }
  const auto topic = sp::parse_topic(topic_text);
  if (!topic || topic->group != settings_.group_id || topic->edge_node != settings_.edge_node_id ||
      (topic->type != sp::MessageType::NCmd && topic->type != sp::MessageType::DCmd)) {
    return bad_message("mqtt: ignored a message on " + topic_text + " (not this node's NCMD/DCMD)");
  }
  std::optional<std::size_t> device;
  if (topic->type == sp::MessageType::DCmd) {
    for (std::size_t i = 0; i < devices_.size(); ++i) {
      if (devices_[i].id == topic->device) device = i;
    }
    if (!device) {
      return bad_message("mqtt: refused the DCMD on " + topic_text + ": no device `" + topic->device +
                         "` on this node (devices are the servo names, else unit-<N>)");
    }
  }
  // Metrics without a datatype (as commands should be sent) are read as their birth said.
  const auto payload = sp::decode(bytes, [&](std::string_view name) { return birth_type(device, name); });
  if (!payload) return bad_message("mqtt: refused the command on " + topic_text + ": " + payload.error());
  if (payload->metrics.empty()) {
    return bad_message("mqtt: ignored the " + std::string(sp::to_string(topic->type)) + " on " + topic_text +
                       ": it carries no metric (" + std::to_string(bytes.size()) + " bytes)");
  }
  for (const auto& metric : payload->metrics) {
    if (commands_.size() >= kMaxQueuedCommands) {
      refuse_command(
          device, metric.name,
          "the command queue is full (" + std::to_string(kMaxQueuedCommands) + " waiting); the bus is not keeping up");
      continue;
    }
    commands_.push_back(Command{device, metric});
  }
  if (!command_running_) run_next_command();
}

// The datatype `name` has in this node's NBIRTH (no device) or the device's DBIRTH.
sp::DataType SparkplugNode::Impl::birth_type(std::optional<std::size_t> device, std::string_view name) const {
  if (device) {
    for (const auto& slot : devices_[*device].metrics) {
      if (slot.name == name) return field_type(*slot.entry);
    }
    if (name == metric_name::kStatus) return sp::DataType::UInt16;
    if (name == metric_name::kRepliesOk || name == metric_name::kTimeouts) return sp::DataType::UInt64;
    if (name == metric_name::kLastCommand) return sp::DataType::String;
    return sp::DataType::Unknown;
  }
  if (name == sp::kBdSeqMetric) return sp::DataType::Int64;
  if (name == sp::kRebirthMetric || name == metric_name::kEStop || name == metric_name::kWatchdogTripped) {
    return sp::DataType::Boolean;
  }
  if (name == metric_name::kVersion) return sp::DataType::String;
  for (const auto& heartbeat : heartbeats_) {
    if (heartbeat == name) return sp::DataType::UInt16;
  }
  return sp::DataType::Unknown;
}

void SparkplugNode::Impl::bad_message(const std::string& text) {
  spdlog::warn("{}", text);
  std::lock_guard lock(stats_mutex_);
  ++stats_.bad_messages;
}

void SparkplugNode::Impl::run_next_command() {
  if (commands_.empty()) {
    command_running_ = false;
    return;
  }
  command_running_ = true;
  Command command = std::move(commands_.front());
  commands_.pop_front();
  if (command.device) return run_device_command(*command.device, command.metric);
  run_node_command(command.metric);
}

void SparkplugNode::Impl::run_device_command(std::size_t index, const sp::Metric& metric) {
  Device& device = devices_[index];
  const auto slot = std::find_if(device.metrics.begin(), device.metrics.end(),
                                 [&](const MetricSlot& s) { return s.name == metric.name; });
  if (slot == device.metrics.end()) return finish_command(index, metric.name, "no such metric on this device");
  const RegisterEntry& entry = *slot->entry;
  const auto reg = device_command_value(metric, device.unit->map, entry);
  if (!reg) return finish_command(index, metric.name, reg.error() + "; nothing written");
  const std::int64_t written = field_value(entry, *reg);
  const std::string what = metric.name + " := " + std::to_string(written);
  const std::size_t slot_index = static_cast<std::size_t>(slot - device.metrics.begin());
  ask(device.unit_id, WriteRegistersRequest{fc::kWriteSingleRegister, entry.address, {*reg}},
      [this, index, slot_index, what, written](const Answer& answer) {
        auto& slot = devices_[index].metrics[slot_index];
        if (!answer.ok()) return finish_command(index, slot.name, refusal_text(index, answer), what);
        if (!slot.entry->readable) return finish_command(index, slot.name, "", what);
        read_back(index, slot_index, written, what);
      });
}

// A refused device write in words: the exception, and after a 0x04 the rule that refused it
// (UnitRouter::refusal_reason, as the console says it, without its own "refused: ": the Last
// Command says that once).
std::string SparkplugNode::Impl::refusal_text(std::size_t index, const Answer& answer) const {
  std::string text = answer.error_text();
  if (answer.pdu.size() >= 2 &&
      answer.pdu[1] == static_cast<std::uint8_t>(modbus_map::ModbusException::ServerDeviceFailure) &&
      answer.refusal.empty()) {
    constexpr std::string_view kRefused = "refused: ";
    std::string reason = router_.refusal_reason(*devices_[index].unit).text;
    if (reason.starts_with(kRefused)) reason.erase(0, kRefused.size());
    text += ": " + reason;
  }
  return text;
}

// After a write, the field as the servo now holds it (FC03, live): a servo may clamp or refuse
// a value silently (a goal below its angle limit holds the limit), and the host must see that,
// not the value it sent.
void SparkplugNode::Impl::read_back(std::size_t index, std::size_t slot_index, std::int64_t written,
                                    const std::string& what) {
  const RegisterEntry& entry = *devices_[index].metrics[slot_index].entry;
  ask(devices_[index].unit_id, ReadRegistersRequest{fc::kReadHoldingRegisters, entry.address, 1},
      [this, index, slot_index, written, what](const Answer& answer) {
        Device& device = devices_[index];
        auto& slot = device.metrics[slot_index];
        const auto registers = answer.registers();
        if (!answer.ok() || registers.empty()) {
          return finish_command(index, slot.name, "", what + " (read-back failed: " + answer.error_text() + ")");
        }
        const std::int64_t held = field_value(*slot.entry, registers[0]);
        slot.value = held;
        finish_command(index, slot.name, "", held != written ? what + ", reads back " + std::to_string(held) : what,
                       device.born);
      });
}

// Ends a device command: logs a refusal, records "ok: DONE" or "refused: DONE: REFUSAL" (DONE: the
// write, "goal_position := 1500", or the metric's name where nothing was written) as the device's
// Gateway/Last Command and publishes it (with the value read back after a write).
void SparkplugNode::Impl::finish_command(std::size_t index, const std::string& name, const std::string& refusal,
                                         const std::string& done, bool report_value) {
  Device& device = devices_[index];
  {
    std::lock_guard lock(stats_mutex_);
    ++(refusal.empty() ? stats_.commands_ok : stats_.commands_refused);
  }
  if (refusal.empty()) {
    device.last_command = "ok: " + done;
  } else {
    const std::string& what = done.empty() ? name : done;
    device.last_command = "refused: " + what + ": " + refusal;
    spdlog::warn("mqtt: DCMD for {} (unit {}) refused: {}: {}", device.id, device.unit_id, what, refusal);
  }
  if (session_ && device.born) {
    sp::Payload payload;
    if (report_value) {
      const auto& slot = *std::find_if(device.metrics.begin(), device.metrics.end(),
                                       [&](const MetricSlot& s) { return s.name == name; });
      payload.metrics.push_back(field_metric(slot.name, *slot.entry, slot.value));
    }
    payload.metrics.push_back(sp::Metric::string(std::string(metric_name::kLastCommand), device.last_command));
    publish(sp::MessageType::DData, std::move(payload), device.id);
  }
  run_next_command();
}

void SparkplugNode::Impl::run_node_command(const sp::Metric& metric) {
  const auto done = [this, name = metric.name](const Answer& answer) {
    finish_node_command(name, answer.ok() ? "" : answer.error_text());
  };
  const std::uint8_t gateway = config_.modbus_tcp.gateway_unit_id;
  const sp::DataType born_as = birth_type(std::nullopt, metric.name);
  // The Boolean controls and the UInt16 heartbeats; bdSeq and the version are the node's own.
  const bool writable = born_as == sp::DataType::Boolean || born_as == sp::DataType::UInt16;
  if (born_as == sp::DataType::Unknown || !writable) {
    return finish_node_command(metric.name, born_as == sp::DataType::Unknown ? "no such node metric" : "read-only");
  }
  const auto value = command_value(metric, born_as);  // Boolean 0/1, UInt16 0..65535: the registers' range
  if (!value) return finish_node_command(metric.name, value.error() + "; nothing written");
  if (metric.name == sp::kRebirthMetric) {
    if (*value != 0 && session_) node_birth();  // NBIRTH again, then every DBIRTH
    return finish_node_command(metric.name, "");
  }
  if (metric.name == metric_name::kEStop) {
    return ask(gateway, WriteBitsRequest{fc::kWriteSingleCoil, gateway_unit_layout::kEStopCoil, {*value != 0}}, done);
  }
  if (metric.name == metric_name::kWatchdogTripped) {
    if (*value != 0) return finish_node_command(metric.name, "only false (re-arm) can be written");
    return ask(gateway, WriteBitsRequest{fc::kWriteSingleCoil, gateway_unit_layout::kWatchdogCoil, {false}}, done);
  }
  for (std::size_t bus = 0; bus < heartbeats_.size(); ++bus) {
    if (metric.name != heartbeats_[bus]) continue;
    return ask(gateway,
               WriteRegistersRequest{fc::kWriteSingleRegister,
                                     static_cast<std::uint16_t>(config::kHeartbeatRegisterBase + bus),
                                     {static_cast<std::uint16_t>(*value)}},
               done);
  }
  finish_node_command(metric.name, "no such node metric");
}

void SparkplugNode::Impl::finish_node_command(const std::string& name, const std::string& refusal) {
  {
    std::lock_guard lock(stats_mutex_);
    ++(refusal.empty() ? stats_.commands_ok : stats_.commands_refused);
  }
  if (!refusal.empty()) spdlog::warn("mqtt: NCMD refused: {}: {}", name, refusal);
  run_next_command();
}

void SparkplugNode::Impl::refuse_command(std::optional<std::size_t> device, const std::string& name,
                                         const std::string& why) {
  std::lock_guard lock(stats_mutex_);
  ++stats_.commands_refused;
  spdlog::warn("mqtt: {} refused: {}: {}", device ? "DCMD for " + devices_[*device].id : std::string("NCMD"), name,
               why);
}

}  // namespace sms::gateway
