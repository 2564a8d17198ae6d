// dump_config(): the configuration back as YAML, every key written out (config/README.md order).
#include <yaml-cpp/yaml.h>

#include "config/load.h"
#include "modbus_map/tables.h"

namespace sms::config {
namespace {

void key(YAML::Emitter& out, const char* name) { out << YAML::Key << name << YAML::Value; }

// An empty list reads `[]`, not a block list with nothing in it.
void begin_list(YAML::Emitter& out, bool empty) {
  if (empty) out << YAML::Flow;
  out << YAML::BeginSeq;
}

// Free text (paths, labels) is always quoted so that e.g. a name "null" or "123" stays a string.
void quoted(YAML::Emitter& out, const std::string& text) { out << YAML::DoubleQuoted << text; }

void emit_modbus_tcp(YAML::Emitter& out, const ModbusTcpConfig& tcp) {
  key(out, "modbus_tcp");
  out << YAML::BeginMap;
  key(out, "listen");
  out << tcp.listen.to_string();
  key(out, "max_connections");
  out << tcp.max_connections;
  key(out, "max_waiting");
  out << tcp.max_waiting;
  key(out, "max_waiting_per_address");
  out << tcp.max_waiting_per_address;
  key(out, "first_request_timeout_ms");
  out << tcp.first_request_timeout.count();
  key(out, "idle_timeout_s");
  out << tcp.idle_timeout.count();
  key(out, "gateway_unit_id");
  out << static_cast<unsigned>(tcp.gateway_unit_id);
  key(out, "request_queue_depth");
  out << tcp.request_queue_depth;
  if (!tcp.allow.empty()) {  // absent: every client (an empty list is refused by the loader)
    key(out, "allow");
    out << YAML::Flow << YAML::BeginSeq;
    for (const auto& network : tcp.allow) quoted(out, network.to_string());
    out << YAML::EndSeq;
  }
  key(out, "plain");
  out << tcp.plain;
  if (tcp.tls) {  // absent: no Modbus/TCP Security listener
    key(out, "tls");
    out << YAML::BeginMap;
    key(out, "listen");
    out << tcp.tls->listen.to_string();
    key(out, "certificate");
    quoted(out, tcp.tls->certificate);
    key(out, "private_key");
    quoted(out, tcp.tls->private_key);
    key(out, "ca");
    quoted(out, tcp.tls->ca);
    key(out, "roles");
    if (tcp.tls->roles.empty()) out << YAML::Flow;
    out << YAML::BeginMap;
    for (const auto& mapping : tcp.tls->roles) {
      out << YAML::Key << YAML::DoubleQuoted << mapping.name << YAML::Value << std::string(to_string(mapping.role));
    }
    out << YAML::EndMap;
    key(out, "default_role");
    out << std::string(to_string(tcp.tls->default_role));
    key(out, "role_names");
    if (tcp.tls->role_names.empty()) out << YAML::Flow;
    out << YAML::BeginMap;
    for (const auto& mapping : tcp.tls->role_names) {
      out << YAML::Key << YAML::DoubleQuoted << mapping.name << YAML::Value << std::string(to_string(mapping.role));
    }
    out << YAML::EndMap;
    key(out, "handshake_timeout_ms");
    out << tcp.tls->handshake_timeout.count();
    key(out, "max_handshakes");
    out << tcp.tls->max_handshakes;
    key(out, "max_handshakes_per_address");
    out << tcp.tls->max_handshakes_per_address;
    out << YAML::EndMap;
  }
  out << YAML::EndMap;
}

void emit_mqtt(YAML::Emitter& out, const MqttConfig& mqtt) {
  key(out, "mqtt");
  out << YAML::BeginMap;
  key(out, "broker");
  out << mqtt.broker.to_string();
  key(out, "group_id");
  quoted(out, mqtt.group_id);
  key(out, "edge_node_id");
  quoted(out, mqtt.edge_node_id);
  key(out, "client_id");
  quoted(out, mqtt.client_id);
  if (!mqtt.username.empty()) {
    key(out, "username");
    quoted(out, mqtt.username);
  }
  if (!mqtt.password_file.empty()) {
    key(out, "password_file");
    quoted(out, mqtt.password_file);
  }
  if (mqtt.tls) {
    key(out, "tls");
    out << YAML::BeginMap;
    key(out, "ca");
    quoted(out, mqtt.tls->ca);
    if (!mqtt.tls->certificate.empty()) {
      key(out, "certificate");
      quoted(out, mqtt.tls->certificate);
      key(out, "private_key");
      quoted(out, mqtt.tls->private_key);
    }
    out << YAML::EndMap;
  }
  key(out, "keepalive_s");
  out << mqtt.keepalive.count();
  key(out, "role");
  out << std::string(to_string(mqtt.role));
  key(out, "data_period_ms");
  out << mqtt.data_period.count();
  key(out, "report_period_s");
  out << mqtt.report_period.count();
  key(out, "deadband");
  if (mqtt.deadbands.empty()) out << YAML::Flow;
  out << YAML::BeginMap;
  for (const auto& band : mqtt.deadbands) out << YAML::Key << band.field << YAML::Value << band.deadband;
  out << YAML::EndMap;
  key(out, "reconnect_min_ms");
  out << mqtt.reconnect_min.count();
  key(out, "reconnect_max_ms");
  out << mqtt.reconnect_max.count();
  if (!mqtt.primary_host_id.empty()) {
    key(out, "primary_host_id");
    quoted(out, mqtt.primary_host_id);
  }
  out << YAML::EndMap;
}

void emit_bus(YAML::Emitter& out, const BusConfig& bus) {
  out << YAML::BeginMap;
  key(out, "name");
  out << bus.name;
  key(out, "device");
  quoted(out, bus.device);
  key(out, "protocol");
  out << std::string(protocol::to_string(bus.protocol));
  key(out, "baud");
  out << bus.baud;
  key(out, "parity");
  out << std::string(to_string(bus.parity));
  key(out, "stop_bits");
  out << static_cast<unsigned>(bus.stop_bits);
  key(out, "response_timeout_ms");
  out << bus.response_timeout.count();
  key(out, "retries");
  out << bus.retries;
  key(out, "poll_period_ms");
  out << bus.poll_period.count();
  key(out, "offline_probe_period_ms");
  out << bus.offline_probe_period.count();
  key(out, "reopen_period_ms");
  out << bus.reopen_period.count();
  if (!bus.poll.fields.empty()) {
    key(out, "poll_fields");
    out << YAML::Flow << YAML::BeginSeq;
    for (const auto& field : bus.poll.fields) out << field;
    out << YAML::EndSeq;
  }
  if (bus.poll.range) {
    key(out, "poll_range");
    out << YAML::Flow << YAML::BeginMap;
    key(out, "start");
    out << bus.poll.range->start;
    key(out, "count");
    out << bus.poll.range->count;
    out << YAML::EndMap;
  }
  if (bus.protocol == protocol::BusProtocol::ModbusRtu) {
    key(out, "rs485");
    out << bus.modbus_rtu.rs485;
    key(out, "rts");
    out << std::string(to_string(bus.modbus_rtu.rts));
    if (bus.modbus_rtu.rts_delay) {
      key(out, "rts_delay_us");
      out << bus.modbus_rtu.rts_delay->count();
    }
    key(out, "byte_timeout_ms");
    out << bus.modbus_rtu.byte_timeout.count();
    key(out, "frame_gap");
    out << bus.modbus_rtu.frame_gap.to_string();
  }
  if (bus.watchdog) {
    key(out, "watchdog");
    out << YAML::Flow << YAML::BeginMap;
    key(out, "timeout_ms");
    out << bus.watchdog->timeout.count();
    key(out, "feed");
    out << std::string(to_string(bus.watchdog->feed));
    if (bus.watchdog->action) {
      key(out, "action");
      out << std::string(modbus_map::to_string(*bus.watchdog->action));
    }
    out << YAML::EndMap;
  }
  key(out, "on_start");
  out << std::string(to_string(bus.on_start));
  key(out, "on_stop");
  out << std::string(modbus_map::to_string(bus.on_stop));
  if (bus.stop_deceleration) {
    key(out, "stop_deceleration");
    out << *bus.stop_deceleration;
  }
  out << YAML::EndMap;
}

void emit_servo(YAML::Emitter& out, const ServoConfig& servo) {
  out << YAML::BeginMap;
  key(out, "unit");
  out << static_cast<unsigned>(servo.unit_id);
  key(out, "bus");
  out << servo.bus;
  key(out, "id");
  out << static_cast<unsigned>(servo.servo_id);
  key(out, "table");
  out << (servo.table ? std::string(modbus_map::table(*servo.table).name) : std::string("passthrough"));
  if (servo.table) {
    key(out, "profile");
    out << std::string(to_string(servo.profile));
  }
  if (servo.byte_order) {
    key(out, "byte_order");
    out << std::string(to_string(*servo.byte_order));
  }
  if (servo.response_level) {
    key(out, "response_level");
    out << static_cast<unsigned>(*servo.response_level);
  }
  key(out, "read_only");
  out << servo.read_only;
  if (!servo.name.empty()) {
    key(out, "name");
    quoted(out, servo.name);
  }
  if (servo.safe_stop) {
    key(out, "safe_stop");
    out << std::string(modbus_map::to_string(*servo.safe_stop));
  }
  if (servo.stop_deceleration) {
    key(out, "stop_deceleration");
    out << *servo.stop_deceleration;
  }
  out << YAML::EndMap;
}

void emit_sync_group(YAML::Emitter& out, const SyncGroupConfig& group) {
  out << YAML::BeginMap;
  key(out, "name");
  quoted(out, group.name);
  key(out, "field");
  out << group.field;
  key(out, "members");
  out << YAML::Flow << YAML::BeginSeq;
  for (const auto unit : group.members) out << static_cast<unsigned>(unit);
  out << YAML::EndSeq;
  key(out, "holding_register_start");
  out << group.holding_register_start;
  if (group.move_time) {
    key(out, "move_time");
    out << true;
  }
  if (group.stretch) {
    key(out, "stretch");
    out << true;
  }
  out << YAML::EndMap;
}

void emit_logging(YAML::Emitter& out, const LoggingConfig& logging) {
  key(out, "logging");
  out << YAML::BeginMap;
  key(out, "level");
  out << std::string(to_string(logging.level));
  key(out, "format");
  out << std::string(to_string(logging.format));
  if (logging.metrics_listen) {
    key(out, "metrics_listen");
    out << logging.metrics_listen->to_string();
  }
  out << YAML::EndMap;
}

void emit_rtu_slave(YAML::Emitter& out, const RtuSlaveConfig& port) {
  out << YAML::BeginMap;
  key(out, "device");
  quoted(out, port.device);
  key(out, "baud");
  out << port.baud;
  key(out, "parity");
  out << std::string(to_string(port.parity));
  key(out, "stop_bits");
  out << static_cast<unsigned>(port.stop_bits);
  key(out, "frame_gap");
  out << port.line.frame_gap.to_string();
  key(out, "rs485");
  out << port.line.rs485;
  key(out, "rts");
  out << std::string(to_string(port.line.rts));
  if (port.line.rts_delay) {
    key(out, "rts_delay_us");
    out << port.line.rts_delay->count();
  }
  if (!port.units.empty()) {  // absent: every unit (an empty list is refused by the loader)
    key(out, "units");
    out << YAML::Flow << YAML::BeginSeq;
    for (const auto unit : port.units) out << static_cast<unsigned>(unit);
    out << YAML::EndSeq;
  }
  key(out, "role");
  out << std::string(to_string(port.role));
  key(out, "reopen_period_ms");
  out << port.reopen_period.count();
  key(out, "echo");
  out << std::string(to_string(port.echo));
  out << YAML::EndMap;
}

}  // namespace

void emit_console(YAML::Emitter& out, const ConsoleConfig& console) {
  key(out, "console");
  out << YAML::BeginMap;
  key(out, "listen");
  out << console.listen.to_string();
  key(out, "tls");
  out << console.tls;
  if (!console.certificate.empty()) {
    key(out, "certificate");
    quoted(out, console.certificate);
    key(out, "key");
    quoted(out, console.key);
  }
  if (console.insecure_http) {
    key(out, "insecure_http");
    out << true;
  }
  key(out, "session_timeout_s");
  out << console.session_timeout.count();
  key(out, "users");
  begin_list(out, console.users.empty());
  for (const auto& user : console.users) {
    out << YAML::BeginMap;
    key(out, "name");
    quoted(out, user.name);
    key(out, "role");
    out << std::string(to_string(user.role));
    key(out, "password_hash");
    quoted(out, user.password_hash);
    out << YAML::EndMap;
  }
  out << YAML::EndSeq;
  out << YAML::EndMap;
}

std::string dump_config(const Config& config) {
  YAML::Emitter out;
  out.SetBoolFormat(YAML::TrueFalseBool);
  out << YAML::BeginMap;
  emit_modbus_tcp(out, config.modbus_tcp);
  key(out, "buses");
  begin_list(out, config.buses.empty());
  for (const auto& bus : config.buses) emit_bus(out, bus);
  out << YAML::EndSeq;
  key(out, "servos");
  begin_list(out, config.servos.empty());
  for (const auto& servo : config.servos) emit_servo(out, servo);
  out << YAML::EndSeq;
  key(out, "sync_groups");
  begin_list(out, config.sync_groups.empty());
  for (const auto& group : config.sync_groups) emit_sync_group(out, group);
  out << YAML::EndSeq;
  emit_logging(out, config.logging);
  if (config.mqtt) emit_mqtt(out, *config.mqtt);
  if (!config.state_dir.empty()) {
    key(out, "state_dir");
    quoted(out, config.state_dir);
  }
  if (!config.modbus_rtu_slave.empty()) {
    key(out, "modbus_rtu_slave");
    out << YAML::BeginSeq;
    for (const auto& port : config.modbus_rtu_slave) emit_rtu_slave(out, port);
    out << YAML::EndSeq;
  }
  if (config.console) emit_console(out, *config.console);
  out << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

}  // namespace sms::config
