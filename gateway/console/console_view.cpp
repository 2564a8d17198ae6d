#include "gateway/console/console_view.h"

#include <algorithm>
#include <exception>
#include <string>

#include "gateway/bus/discovery.h"
#include "gateway/service/role_policy.h"
#include "modbus_map/field_unit.h"
#include "modbus_map/motion.h"
#include "modbus_map/status_bits.h"
#include "modbus_map/tables.h"

namespace sms::gateway::console {

namespace {

using modbus_map::RegisterEntry;
using nlohmann::json;

// The input window FC04 serves for the unit (native: the poll block; smsmb profile: 0x100-0x107).
modbus_map::BusRange input_window(const ServoUnit& unit) {
  if (unit.map.profile() == modbus_map::Profile::Smsmb) return modbus_map::kSmsmbFeedbackRegisters;
  return unit.poll_block;
}

std::string_view access_text(modbus_map::Access access) {
  switch (access) {
    case modbus_map::Access::ReadOnly: return "R";
    case modbus_map::Access::WriteOnly: return "W";
    case modbus_map::Access::ReadWrite: return "RW";
  }
  return "?";
}

// What feeds the bus's watchdog, as the safety panel says it.
std::string watchdog_feed_text(const config::BusConfig& bus, std::size_t index) {
  if (!bus.watchdog) return "";
  if (bus.watchdog->feed == config::WatchdogFeed::AnyWrite) return "any carried-out write to a unit of the bus";
  return "a changed value in gateway holding register " + std::to_string(config::kHeartbeatRegisterBase + index);
}

}  // namespace

std::int64_t steady_us(SteadyClock::time_point when) {
  return std::chrono::duration_cast<std::chrono::microseconds>(when.time_since_epoch()).count();
}

std::optional<std::int32_t> PolledValues::value_of(std::string_view field) const {
  for (const auto& [entry, value] : values) {
    if (entry->shown->name == field) return value;
  }
  return std::nullopt;
}

std::int32_t register_to_value(const RegisterEntry& entry, std::uint16_t reg) {
  if (entry.min < 0) return static_cast<std::int16_t>(reg);
  return reg;
}

std::optional<PolledValues> read_polled(const ServoUnit& unit) {
  const modbus_map::BusRange window = input_window(unit);
  const auto plan = unit.map.plan_input_read(window.address, window.count, unit.poll_block);
  if (!plan) return std::nullopt;
  PolledValues polled;
  const PollCache& cache = unit.engine->cache();
  const std::size_t bytes_per_address = cache.bytes_per_address();
  std::vector<protocol::Bytes> replies;
  CachedServoState state;
  for (const auto& range : plan->reads) {
    protocol::Bytes bytes(range.count * bytes_per_address);
    const CacheRead read = cache.copy(unit.servo_id, range.address, bytes, &state);
    if (read != CacheRead::Ok) {
      polled.online = state.online;
      polled.status = state.counters.last_status;
      return polled;  // no data yet: online state only
    }
    replies.push_back(std::move(bytes));
  }
  if (plan->reads.empty()) {
    if (auto only = cache.state(unit.servo_id)) state = *only;
  }
  polled.online = state.online;
  polled.has_data = state.has_data;
  polled.updated = state.updated;
  polled.status = state.counters.last_status;
  const auto registers = unit.map.registers_from(*plan, replies);
  if (!registers) return polled;
  for (const auto& entry : unit.map.entries()) {
    if (!entry.readable || entry.address < window.address || entry.address >= window.address + window.count) continue;
    if (entry.shown->bit_space == modbus_map::BitSpace::Coil && entry.shown->access == modbus_map::Access::WriteOnly)
      continue;
    polled.values.emplace_back(&entry, register_to_value(entry, (*registers)[entry.address - window.address]));
  }
  return polled;
}

std::optional<UnitScale> unit_scale(const modbus_map::FieldSpec& field) {
  const modbus_map::FieldUnit unit = modbus_map::field_unit(field);
  if (field.unit.empty() || !unit.plain) return std::nullopt;
  return UnitScale{unit.scale, std::string(unit.symbol), unit.decimals};
}

json unit_scale_json(const modbus_map::FieldSpec& field) {
  const auto scale = unit_scale(field);
  if (!scale) return nullptr;
  return {{"scale", scale->scale}, {"symbol", scale->symbol}, {"decimals", scale->decimals}};
}

const RegisterEntry* entry_named(const modbus_map::RegisterMap& map, std::string_view field) {
  for (const auto& entry : map.entries()) {
    if (entry.shown->name == field) return &entry;
  }
  return nullptr;
}

const RegisterEntry* entry_for_servo_field(const modbus_map::RegisterMap& map, std::string_view servo_field) {
  if (servo_field.empty()) return nullptr;
  for (const auto& entry : map.entries()) {
    if (entry.counterpart != nullptr && entry.counterpart->name == servo_field && entry.writable) return &entry;
  }
  return nullptr;
}

bool commissioning_only(std::string_view field) { return field == "id" || field == "baud_rate"; }

std::uint64_t poll_wire_floor_us(const config::Config& config, std::size_t bus_index, const UnitRouter& units) {
  const config::BusConfig& bus = config.buses.at(bus_index);
  std::uint64_t bytes = 0;
  std::size_t servos = 0;
  for (const auto& servo : config.servos) {
    if (servo.bus_index != bus_index) continue;
    const ServoUnit* unit = units.servo_unit(servo.unit_id);
    if (unit == nullptr || servo.view_of) continue;
    ++servos;
    const std::uint64_t data = std::uint64_t{unit->poll_block.count} * unit->map.bytes_per_bus_address();
    if (bus.protocol == protocol::BusProtocol::ModbusRtu) {
      bytes += 8 + 5 + data;  // FC03 request, answer
    } else {
      bytes += 6 + data;                                       // each servo's answer: FF FF ID LEN ERR data CHK
      if (!unit->map.servo_table().has_sync_read) bytes += 8;  // one READ each
    }
  }
  if (bus.protocol != protocol::BusProtocol::ModbusRtu && servos > 0) bytes += 8 + servos;  // one SYNC READ request
  return bus.baud == 0 ? 0 : bytes * 10 * 1'000'000 / bus.baud;
}

json overview_json(const config::Config& config, const MetricsSnapshot& metrics, const UnitRouter& units) {
  json gateway = {
      {"version", metrics.version},
      {"uptime_s", metrics.uptime.count()},
      {"connections", metrics.tcp.open_connections},
      {"estop", {{"latched", metrics.estop_latched}, {"count", metrics.estops}}},
      {"safety_state", {{"persisted", !metrics.safety_state_not_persisted}, {"problem", metrics.safety_state_problem}}},
      {"tls", metrics.tls ? json{{"listen", config.modbus_tcp.tls->listen.to_string()}} : json(nullptr)},
      {"mqtt", metrics.mqtt
                   ? json{{"connected", metrics.mqtt->link.connected}, {"broker", config.mqtt->broker.to_string()}}
                   : json(nullptr)},
  };
  json buses = json::array();
  json servos = json::array();
  for (std::size_t b = 0; b < metrics.buses.size() && b < config.buses.size(); ++b) {
    const BusMetrics& bus = metrics.buses[b];
    const config::BusConfig& bus_config = config.buses[b];
    json safety = nullptr;
    if (bus.safety) {
      safety = {{"watchdog", std::string(to_string(bus.safety->state))},
                {"timeout_ms", bus.safety->timeout.count()},
                {"since_feed_ms", bus.safety->since_feed ? json(bus.safety->since_feed->count()) : json(nullptr)},
                {"since_trip_ms", bus.safety->since_trip ? json(bus.safety->since_trip->count()) : json(nullptr)},
                {"feed", watchdog_feed_text(bus_config, b)},
                {"last_cause", std::string(to_string(bus.safety->last_cause))},
                {"trips", bus.safety->trips},
                {"motion_blocked", bus.safety->motion_blocked},
                {"owed_stops", bus.safety->owed_stops},
                {"failed_stops", bus.safety->failed_stops},
                {"lent", bus.safety->lent}};
    }
    buses.push_back({{"name", bus.name},
                     {"device", bus_config.device},
                     {"protocol", bus.protocol},
                     {"baud", bus_config.baud},
                     {"up", bus.up},
                     {"servos_online", bus.servos_online},
                     {"servos", bus.servos.size()},
                     {"poll_cycle_us", bus.counters.last_poll_cycle_us},
                     {"poll_wire_floor_us", poll_wire_floor_us(config, b, units)},
                     {"poll_cycles", bus.counters.poll_cycles},
                     {"timeouts", bus.counters.timeouts},
                     {"queue_depth", config.modbus_tcp.request_queue_depth},
                     {"queue_full", bus.counters.queue_full},
                     {"safety", safety}});
  }
  for (const auto& servo : config.servos) {
    const ServoUnit* unit = units.servo_unit(servo.unit_id);
    if (unit == nullptr) continue;
    json row = {{"unit", servo.unit_id},
                {"id", servo.servo_id},
                {"name", servo.name},
                {"bus", config.buses[servo.bus_index].name},
                {"table", std::string(unit->map.servo_table().name)}};
    const auto state = unit->engine->cache().state(unit->servo_id);
    if (state) {
      // As discovery's log line shows them: "10760 (SM40BL)", "3.10".
      const IdentityLayout* layout = identity_layout(unit->map.servo_table().id);
      row["model"] = format_identity_value(layout, true, state->identity.model);
      row["firmware"] = format_identity_value(layout, false, state->identity.firmware);
    }
    if (const auto polled = read_polled(*unit)) {
      row["online"] = polled->online;
      row["status"] = polled->status;
      row["faults"] = modbus_map::status_faults(unit->map.servo_table().id, polled->status);
      json units = json::object();
      for (const char* field :
           {"present_position", "present_temperature", "present_voltage", "present_load", "present_current"}) {
        const auto value = polled->value_of(field);
        if (!value) continue;
        const std::string key = std::string(field).substr(8);
        row[key] = *value;  // raw, as FC04 reads it
        if (const auto* entry = entry_named(unit->map, field)) units[key] = unit_scale_json(*entry->shown);
      }
      row["units"] = std::move(units);
    }
    servos.push_back(std::move(row));
  }
  return {{"type", "overview"}, {"gateway", gateway}, {"buses", buses}, {"servos", servos}};
}

// The fields that move this unit's servo, by the names its map shows (modbus_map/motion.h): the
// jog reads its limits from these, whatever the table calls them ("" where it has none).
json motion_fields_json(const ServoUnit& unit) {
  const modbus_map::MotionSpec& motion = modbus_map::motion_spec(unit.map.shown_table().id);
  return {{"goal_position", motion.goal_position},
          {"goal_speed", motion.goal_speed},
          {"present_position", motion.present_position},
          {"torque", motion.torque},
          {"min_limit", motion.min_limit},
          {"max_limit", motion.max_limit}};
}

json servo_description_json(const config::Config& config, const ServoUnit& unit) {
  const config::ServoConfig* servo = config::find_unit(config, unit.unit_id);
  json fields = json::array();
  const modbus_map::BusRange window =
      unit.map.profile() == modbus_map::Profile::Smsmb ? modbus_map::kSmsmbFeedbackRegisters : unit.poll_block;
  for (const auto& entry : unit.map.entries()) {
    const auto& field = *entry.shown;
    const bool eeprom = entry.counterpart != nullptr && entry.counterpart->area == modbus_map::Area::Eeprom;
    json allowed = json::array();
    for (const auto value : field.allowed_values) allowed.push_back(value);
    fields.push_back({{"name", field.name},
                      {"address", entry.address},
                      {"unit", field.unit},
                      {"scale", unit_scale_json(field)},
                      {"min", entry.min},
                      {"max", entry.max},
                      {"area", eeprom ? "EEPROM" : "RAM"},
                      {"access", access_text(field.access)},
                      {"readable", entry.readable},
                      {"writable", entry.writable && !unit.read_only},
                      {"engineer", entry.counterpart != nullptr && engineer_only_field(*entry.counterpart)},
                      {"commissioning", commissioning_only(field.name)},
                      {"polled", entry.address >= window.address && entry.address < window.address + window.count},
                      {"allowed", allowed},
                      {"notes", field.notes}});
  }
  return {{"unit", unit.unit_id},
          {"id", unit.servo_id},
          {"name", servo ? servo->name : ""},
          {"bus", config.buses.at(unit.bus_index).name},
          {"table", std::string(unit.map.servo_table().name)},
          {"map", unit.map.description()},
          {"read_only", unit.read_only},
          {"poll_period_ms", config.buses.at(unit.bus_index).poll_period.count()},
          {"motion", motion_fields_json(unit)},
          {"fields", fields}};
}

}  // namespace sms::gateway::console
