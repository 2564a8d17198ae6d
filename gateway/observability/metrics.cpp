#include "gateway/observability/metrics.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>
#include <variant>

#include "gateway/bus/bus_engine.h"
#include "gateway/modbus_tcp/access_policy.h"
#include "protocol/bus_protocol.h"
#include "protocol/modbus_pdu.h"
#include "protocol/modbus_tcp.h"

namespace sms::gateway {
namespace {

// ---- the exposition format ----

enum class MetricType : std::uint8_t { Counter, Gauge };

using Value = std::variant<std::uint64_t, double>;

struct Label {
  std::string_view name;
  std::string value;
};
using Labels = std::vector<Label>;

// Label values escape backslash, double quote and line feed; HELP text backslash and line feed.
void append_escaped(std::string& out, std::string_view text, bool quotes) {
  for (const char c : text) {
    if (c == '\\') {
      out += "\\\\";
    } else if (c == '\n') {
      out += "\\n";
    } else if (quotes && c == '"') {
      out += "\\\"";
    } else {
      out += c;
    }
  }
}

void append_value(std::string& out, const Value& value) {
  char text[32];
  std::to_chars_result result{};
  if (const auto* integer = std::get_if<std::uint64_t>(&value)) {
    result = std::to_chars(std::begin(text), std::end(text), *integer);
  } else if (std::isnan(std::get<double>(value))) {
    out += "NaN";  // the exposition format's spelling (to_chars writes "nan")
    return;
  } else {
    result = std::to_chars(std::begin(text), std::end(text), std::get<double>(value));
  }
  out.append(text, result.ptr);
}

class Exposition {
 public:
  void family(std::string_view name, MetricType type, std::string_view help) {
    out_ += "# HELP ";
    out_ += name;
    out_ += ' ';
    append_escaped(out_, help, false);
    out_ += "\n# TYPE ";
    out_ += name;
    out_ += type == MetricType::Counter ? " counter\n" : " gauge\n";
  }

  void sample(std::string_view name, const Labels& labels, const Value& value) {
    out_ += name;
    if (!labels.empty()) {
      out_ += '{';
      for (std::size_t i = 0; i < labels.size(); ++i) {
        if (i > 0) out_ += ',';
        out_ += labels[i].name;
        out_ += "=\"";
        append_escaped(out_, labels[i].value, true);
        out_ += '"';
      }
      out_ += '}';
    }
    out_ += ' ';
    append_value(out_, value);
    out_ += '\n';
  }

  std::string take() { return std::move(out_); }

 private:
  std::string out_;
};

double seconds(std::chrono::microseconds duration) { return static_cast<double>(duration.count()) / 1e6; }

// ---- families, as data ----

template <typename Subject>
struct Family {
  std::string_view name;
  MetricType type;
  std::string_view help;
  std::optional<Value> (*value)(const Subject&);  // nullopt: no sample for this subject
};

constexpr Family<BusMetrics> kBusFamilies[] = {
    {"sms_gateway_bus_up", MetricType::Gauge, "1 when the bus's serial port is open, 0 while it is down (Modbus 0x0A)",
     [](const BusMetrics& b) -> std::optional<Value> { return std::uint64_t{b.up ? 1u : 0u}; }},
    {"sms_gateway_bus_servos", MetricType::Gauge, "Servos the bus polls",
     [](const BusMetrics& b) -> std::optional<Value> { return std::uint64_t{b.servos.size()}; }},
    {"sms_gateway_bus_servos_online", MetricType::Gauge, "Servos that answered their last poll or probe",
     [](const BusMetrics& b) -> std::optional<Value> { return std::uint64_t{b.servos_online}; }},
    {"sms_gateway_bus_last_poll_cycle_seconds", MetricType::Gauge, "Duration of the last finished poll cycle",
     [](const BusMetrics& b) -> std::optional<Value> {
       return seconds(std::chrono::microseconds{b.counters.last_poll_cycle_us});
     }},
    {"sms_gateway_bus_poll_cycles_total", MetricType::Counter, "Finished poll cycles",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.poll_cycles; }},
    {"sms_gateway_bus_frames_ok_total", MetricType::Counter, "Valid reply frames taken as an answer",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.frames_ok; }},
    {"sms_gateway_bus_timeouts_total", MetricType::Counter,
     "Expected replies that did not come in time (every attempt, every servo of a SYNC READ)",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.timeouts; }},
    {"sms_gateway_bus_checksum_errors_total", MetricType::Counter,
     "Frames with a wrong checksum or CRC, or an impossible length (framing)",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.checksum_errors; }},
    {"sms_gateway_bus_stray_frames_total", MetricType::Counter,
     "Valid frames that were not the awaited answer (late replies, echoes, other IDs)",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.stray_frames; }},
    {"sms_gateway_bus_discarded_bytes_total", MetricType::Counter,
     "Bytes dropped while hunting for a frame header in an awaited answer (noise, damaged frames)",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.discarded_bytes; }},
    {"sms_gateway_bus_stray_bytes_total", MetricType::Counter,
     "Bytes that came when no answer was awaited (late answers, noise): dropped, never taken for an answer",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.stray_bytes; }},
    {"sms_gateway_bus_fences_total", MetricType::Counter,
     "Fence reads sent before a request whose servo still owed late answers that could look like its answer",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.fences; }},
    {"sms_gateway_bus_retries_total", MetricType::Counter, "Attempts after the first one",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.retries; }},
    {"sms_gateway_bus_transactions_total", MetricType::Counter, "Bus operations finished, whatever their outcome",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.transactions; }},
    // docs/PLC_GUIDE.md "Safety".
    {"sms_gateway_watchdog_state", MetricType::Gauge,
     "The bus's watchdog: 1 armed, 2 running, 3 tripped (buses with a watchdog only)",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety || b.safety->state == WatchdogState::Off) return std::nullopt;
       return std::uint64_t{static_cast<std::uint8_t>(b.safety->state)};
     }},
    {"sms_gateway_watchdog_trips_total", MetricType::Counter, "Times the bus's watchdog tripped",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       return b.safety->trips;
     }},
    {"sms_gateway_safe_stops_total", MetricType::Counter,
     "Safe stops performed on the bus (watchdog, e-stop, on_start, on_stop)",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       return b.safety->stops;
     }},
    {"sms_gateway_safe_stops_failed_total", MetricType::Counter,
     "Safe stops that could not be delivered to every servo when performed (bus down, servo offline or "
     "silent); each such servo is owed its stop until it takes it",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       return b.safety->failed_stops;
     }},
    {"sms_gateway_safe_stops_owed", MetricType::Gauge,
     "Servos owed a safe stop right now (sent as soon as the bus and the servo are back)",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       return std::uint64_t{b.safety->owed_stops};
     }},
    {"sms_gateway_safe_stop_latency_seconds", MetricType::Gauge,
     "Last safe stop: from the last feed (watchdog) or the request to its frames on the wire; NaN before the first "
     "stop and after one that failed",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       // The series stays (an alert on it must not see it vanish): NaN says there is no figure.
       if (!b.safety->last_stop_latency) return std::numeric_limits<double>::quiet_NaN();
       return seconds(*b.safety->last_stop_latency);
     }},
    {"sms_gateway_motion_blocked", MetricType::Gauge,
     "1 while motion writes to the bus are refused (e-stop latched or watchdog tripped)",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.safety) return std::nullopt;
       return std::uint64_t{b.safety->motion_blocked ? 1u : 0u};
     }},
    {"sms_gateway_bus_queue_full_total", MetricType::Counter,
     "Client requests refused because the bus queue was full (Modbus 0x06)",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.queue_full; }},
    {"sms_gateway_bus_down_events_total", MetricType::Counter,
     "Times the serial port was lost, or could not be reopened after a loss",
     [](const BusMetrics& b) -> std::optional<Value> { return b.counters.bus_down_events; }},
    // docs/MONITOR.md.
    {"sms_gateway_monitor_dropped_total", MetricType::Counter,
     "Bus monitor records overwritten before a reader (the console's live view) got them: the reader was too slow",
     [](const BusMetrics& b) -> std::optional<Value> {
       if (!b.monitor_dropped) return std::nullopt;
       return *b.monitor_dropped;
     }},
};

constexpr Family<ServoMetrics> kServoFamilies[] = {
    {"sms_gateway_servo_online", MetricType::Gauge, "1 when the servo answered its last poll or probe",
     [](const ServoMetrics& s) -> std::optional<Value> { return std::uint64_t{s.online ? 1u : 0u}; }},
    {"sms_gateway_servo_offline_reason", MetricType::Gauge,
     "Why the servo is offline: 0 online, 1 no answer, 2 answers late (probed only; input register 1008)",
     [](const ServoMetrics& s) -> std::optional<Value> {
       return std::uint64_t{static_cast<unsigned>(s.offline_reason)};
     }},
    {"sms_gateway_servo_late_answers_total", MetricType::Counter,
     "Answers from the servo that came after their request had given up",
     [](const ServoMetrics& s) -> std::optional<Value> { return s.counters.late_answers; }},
    {"sms_gateway_servo_heartbeat_gaps_total", MetricType::Counter,
     "d55d: times the motor went longer than its 500 ms heartbeat without an instruction (it stops itself if moving)",
     [](const ServoMetrics& s) -> std::optional<Value> { return s.counters.heartbeat_gaps; }},
    {"sms_gateway_servo_cache_age_seconds", MetricType::Gauge,
     "Age of the servo's polled data (input registers); absent until the first successful poll",
     [](const ServoMetrics& s) -> std::optional<Value> {
       if (!s.cache_age) return std::nullopt;
       return seconds(*s.cache_age);
     }},
    {"sms_gateway_servo_last_status", MetricType::Gauge,
     "Status / ERROR byte of the servo's latest answer (input register 1000)",
     [](const ServoMetrics& s) -> std::optional<Value> { return std::uint64_t{s.counters.last_status}; }},
    {"sms_gateway_servo_replies_ok_total", MetricType::Counter, "Valid answers from the servo",
     [](const ServoMetrics& s) -> std::optional<Value> { return s.counters.replies_ok; }},
    {"sms_gateway_servo_timeouts_total", MetricType::Counter,
     "Attempts addressed to the servo that got no valid answer",
     [](const ServoMetrics& s) -> std::optional<Value> { return s.counters.timeouts; }},
};

constexpr Family<TcpServerStats> kTcpFamilies[] = {
    {"sms_gateway_tcp_connections", MetricType::Gauge, "Modbus TCP connections open now",
     [](const TcpServerStats& t) -> std::optional<Value> { return std::uint64_t{t.open_connections}; }},
    {"sms_gateway_tcp_connections_accepted_total", MetricType::Counter, "Modbus TCP connections accepted",
     [](const TcpServerStats& t) -> std::optional<Value> { return t.accepted; }},
    {"sms_gateway_tcp_connections_closed_idle_total", MetricType::Counter,
     "Connections closed after modbus_tcp.idle_timeout_s without a request",
     [](const TcpServerStats& t) -> std::optional<Value> { return t.idle_closed; }},
    {"sms_gateway_tcp_bad_headers_total", MetricType::Counter,
     "Connections closed for an MBAP header that is not Modbus TCP",
     [](const TcpServerStats& t) -> std::optional<Value> { return t.bad_headers; }},
};

std::string hex_code(std::uint8_t code) {
  constexpr char kDigits[] = "0123456789ABCDEF";
  return {'0', 'x', kDigits[code >> 4], kDigits[code & 0x0F]};
}

Labels bus_labels(const BusMetrics& bus) { return {{"bus", bus.name}, {"protocol", bus.protocol}}; }

Labels servo_labels(const BusMetrics& bus, const ServoMetrics& servo) {
  Labels labels{{"bus", bus.name}, {"unit", std::to_string(servo.unit_id)}, {"servo", std::to_string(servo.servo_id)}};
  // An empty label value means "no such label" to Prometheus: leave it out instead.
  if (!servo.name.empty()) labels.push_back({"name", servo.name});
  return labels;
}

void render_requests(Exposition& out, const ModbusTrafficSnapshot& traffic) {
  constexpr std::string_view kName = "sms_gateway_modbus_requests_total";
  out.family(kName, MetricType::Counter, "Modbus TCP requests received, by function code");
  for (unsigned code = 0; code < traffic.requests_by_function.size(); ++code) {
    const auto* function = find_modbus_function(static_cast<std::uint8_t>(code));
    const std::uint64_t count = traffic.requests_by_function[code];
    if (count == 0 && !(function && function->served)) continue;
    out.sample(kName,
               {{"function", std::to_string(code)}, {"name", std::string(function ? function->name : "unknown")}},
               count);
  }
}

void render_exceptions(Exposition& out, const ModbusTrafficSnapshot& traffic) {
  constexpr std::string_view kName = "sms_gateway_modbus_exceptions_total";
  out.family(kName, MetricType::Counter, "Modbus exception answers sent, by exception code");
  for (unsigned code = 0; code < traffic.exceptions_by_code.size(); ++code) {
    const auto* exception = protocol::find_modbus_exception(static_cast<std::uint8_t>(code));
    const std::uint64_t count = traffic.exceptions_by_code[code];
    // The codes docs/PLC_GUIDE.md says the gateway answers with are always shown (at 0), so that
    // rate() works from the start.
    if (count == 0 && !(exception && exception->contract)) continue;
    out.sample(kName,
               {{"code", hex_code(static_cast<std::uint8_t>(code))},
                {"name", std::string(exception ? exception->label : "unknown")}},
               count);
  }
}

}  // namespace

// ---- collecting ----

BusMetrics read_bus_metrics(const config::Config& config, std::size_t bus_index, bool up,
                            const BusCountersSnapshot& counters, const PollCache& cache, SteadyClock::time_point now) {
  const config::BusConfig& bus = config.buses.at(bus_index);
  BusMetrics metrics;
  metrics.name = bus.name;
  metrics.protocol = std::string(protocol::to_string(bus.protocol));
  metrics.up = up;
  metrics.counters = counters;
  metrics.servos_online = cache.online_count();
  for (const auto& servo : config.servos) {
    if (servo.bus_index != bus_index || servo.passthrough() || servo.view_of) continue;  // one sample per servo
    const auto state = cache.state(servo.servo_id);
    if (!state) continue;
    ServoMetrics entry;
    entry.unit_id = servo.unit_id;
    entry.servo_id = servo.servo_id;
    entry.name = servo.name;
    entry.online = state->online;
    entry.offline_reason = state->offline_reason;
    if (const auto age = state->age(now)) {
      entry.cache_age =
          std::max(std::chrono::duration_cast<std::chrono::microseconds>(*age), std::chrono::microseconds{0});
    }
    entry.counters = state->counters;
    metrics.servos.push_back(std::move(entry));
  }
  return metrics;
}

MetricsSnapshot collect_metrics(const config::Config& config, std::span<BusEngine* const> engines,
                                const TcpServerStats& tcp, const ModbusTrafficCounters& traffic,
                                SteadyClock::time_point started, SteadyClock::time_point now,
                                const SafetyFacts* safety) {
  MetricsSnapshot snapshot;
  snapshot.version = SMS_GATEWAY_VERSION;
  snapshot.uptime = std::chrono::duration_cast<std::chrono::seconds>(now - started);
  for (std::size_t i = 0; i < engines.size() && i < config.buses.size(); ++i) {
    const BusEngine* engine = engines[i];
    if (engine == nullptr) continue;
    snapshot.buses.push_back(read_bus_metrics(config, i, engine->bus_up(), engine->counters(), engine->cache(), now));
    if (safety != nullptr && i < safety->buses.size()) snapshot.buses.back().safety = safety->buses[i];
  }
  if (safety != nullptr) {
    snapshot.estop_latched = safety->estop_latched;
    snapshot.estops = safety->estops;
    snapshot.safety_state_not_persisted = safety->state_not_persisted;
    snapshot.safety_state_problem = safety->state_problem;
  }
  snapshot.tcp = tcp;
  snapshot.traffic = traffic.snapshot();
  return snapshot;
}

// ---- rendering ----

namespace {

// Every TCP listener's door: the same three families whichever way in it is.
void render_listener_doors(Exposition& out, const std::vector<ListenerDoor>& listeners) {
  constexpr std::string_view kOpen = "sms_gateway_listener_connections";
  out.family(kOpen, MetricType::Gauge,
             "Connections open now by listener (plain, tls, console, metrics) and state: waiting for their first "
             "complete request, handshake or login, or served");
  for (const auto& listener : listeners) {
    out.sample(kOpen, {{"listener", listener.listener}, {"state", "waiting"}}, std::uint64_t{listener.door.waiting});
    out.sample(kOpen, {{"listener", listener.listener}, {"state", "served"}}, std::uint64_t{listener.door.served});
  }
  constexpr std::string_view kAccepted = "sms_gateway_listener_accepted_total";
  out.family(kAccepted, MetricType::Counter, "Connections let in by listener");
  for (const auto& listener : listeners)
    out.sample(kAccepted, {{"listener", listener.listener}}, listener.door.accepted);
  constexpr std::string_view kClosed = "sms_gateway_listener_closed_total";
  out.family(kClosed, MetricType::Counter,
             "Connections the listener's door closed, by reason: full (the served budget), evicted (to make room "
             "for a newer one), deadline (no complete first request or handshake in time), allow (not in the "
             "allow-list)");
  for (const auto& listener : listeners) {
    for (std::size_t i = 0; i < kDoorCloseNames.size(); ++i) {
      out.sample(kClosed, {{"listener", listener.listener}, {"reason", std::string(kDoorCloseNames[i])}},
                 listener.door.closed[i]);
    }
  }
}

}  // namespace

std::string render_prometheus(const MetricsSnapshot& snapshot) {
  Exposition out;
  out.family("sms_gateway_build_info", MetricType::Gauge, "Always 1; the version is in the label");
  out.sample("sms_gateway_build_info", {{"version", snapshot.version}}, std::uint64_t{1});
  out.family("sms_gateway_uptime_seconds", MetricType::Gauge, "Seconds since the gateway started");
  out.sample("sms_gateway_uptime_seconds", {},
             static_cast<std::uint64_t>(std::max<std::int64_t>(snapshot.uptime.count(), 0)));

  for (const auto& family : kBusFamilies) {
    out.family(family.name, family.type, family.help);
    for (const auto& bus : snapshot.buses) {
      if (const auto value = family.value(bus)) out.sample(family.name, bus_labels(bus), *value);
    }
  }
  for (const auto& family : kServoFamilies) {
    out.family(family.name, family.type, family.help);
    for (const auto& bus : snapshot.buses) {
      for (const auto& servo : bus.servos) {
        if (const auto value = family.value(servo)) out.sample(family.name, servo_labels(bus, servo), *value);
      }
    }
  }
  for (const auto& family : kTcpFamilies) {
    out.family(family.name, family.type, family.help);
    if (const auto value = family.value(snapshot.tcp)) out.sample(family.name, {}, *value);
  }
  constexpr std::string_view kRefused = "sms_gateway_tcp_connections_refused_total";
  out.family(kRefused, MetricType::Counter,
             "Connections closed at once, by listener (plain, tls): over modbus_tcp.max_connections, or not in "
             "modbus_tcp.allow");
  for (std::size_t i = 0; i < kListenerNames.size(); ++i) {
    if (kListenerNames[i] == "tls" && !snapshot.tls) continue;
    const std::string listener(kListenerNames[i]);
    out.sample(kRefused, {{"listener", listener}, {"reason", "max_connections"}},
               snapshot.tcp.refusals[i].max_connections);
    out.sample(kRefused, {{"listener", listener}, {"reason", "allow"}}, snapshot.tcp.refusals[i].allow);
  }

  render_listener_doors(out, snapshot.listeners);

  if (snapshot.tls) {
    const TlsStats& tls = *snapshot.tls;
    constexpr std::string_view kHandshakes = "sms_gateway_tls_handshakes_total";
    out.family(kHandshakes, MetricType::Counter,
               "Modbus/TCP Security handshakes by outcome (ok, expired, unknown_ca, no_certificate, not_tls, ...)");
    for (std::size_t i = 0; i < kHandshakeResults.size(); ++i) {
      out.sample(kHandshakes, {{"result", std::string(kHandshakeResults[i])}}, tls.handshakes[i]);
    }
    out.family("sms_gateway_tls_connections", MetricType::Gauge,
               "Modbus/TCP Security connections open now (handshake done, role given)");
    out.sample("sms_gateway_tls_connections", {}, std::uint64_t{tls.open_connections});
    constexpr std::string_view kRefusedRequests = "sms_gateway_tls_requests_refused_total";
    out.family(kRefusedRequests, MetricType::Counter,
               "Requests answered with an exception because the certificate's role may not make them");
    out.sample(kRefusedRequests, {{"role", "read"}}, tls.requests_refused_read);
    out.sample(kRefusedRequests, {{"role", "operate"}}, tls.requests_refused_operate);
    constexpr std::string_view kReloads = "sms_gateway_tls_reloads_total";
    out.family(kReloads, MetricType::Counter,
               "Certificate reloads (SIGHUP) by outcome; a failed one keeps the old files");
    out.sample(kReloads, {{"result", "ok"}}, tls.reloads_ok);
    out.sample(kReloads, {{"result", "failed"}}, tls.reloads_failed);
  }

  if (snapshot.mqtt) {
    const SparkplugStats& mqtt = *snapshot.mqtt;
    out.family("sms_gateway_mqtt_connected", MetricType::Gauge, "1 while the Sparkplug edge node has a broker session");
    out.sample("sms_gateway_mqtt_connected", {}, std::uint64_t{mqtt.link.connected ? 1u : 0u});
    constexpr std::string_view kSessions = "sms_gateway_mqtt_sessions_total";
    out.family(kSessions, MetricType::Counter,
               "Broker sessions by event: connected, failed (attempt without a session), lost");
    out.sample(kSessions, {{"event", "connected"}}, mqtt.link.connects);
    out.sample(kSessions, {{"event", "failed"}}, mqtt.link.connect_failures);
    out.sample(kSessions, {{"event", "lost"}}, mqtt.link.disconnects);
    constexpr std::string_view kMessages = "sms_gateway_mqtt_messages_published_total";
    out.family(kMessages, MetricType::Counter, "Sparkplug messages published by type");
    constexpr std::array<std::string_view, 6> kTypes{"NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA", "DDATA"};
    for (std::size_t i = 0; i < kTypes.size(); ++i)
      out.sample(kMessages, {{"type", std::string(kTypes[i])}}, mqtt.published[i]);
    out.family("sms_gateway_mqtt_publish_failures_total", MetricType::Counter,
               "Messages not handed to the broker (no session at the time)");
    out.sample("sms_gateway_mqtt_publish_failures_total", {}, mqtt.link.publish_failures);
    constexpr std::string_view kCommands = "sms_gateway_mqtt_commands_total";
    out.family(kCommands, MetricType::Counter, "NCMD/DCMD metrics by result (refused: see the log for why)");
    out.sample(kCommands, {{"result", "ok"}}, mqtt.commands_ok);
    out.sample(kCommands, {{"result", "refused"}}, mqtt.commands_refused);
    out.family("sms_gateway_mqtt_bad_messages_total", MetricType::Counter,
               "Messages on the command topics that are not a Sparkplug payload or name no device of this node");
    out.sample("sms_gateway_mqtt_bad_messages_total", {}, mqtt.bad_messages);
    out.family("sms_gateway_mqtt_devices_online", MetricType::Gauge, "Devices born (DBIRTH sent) on the broker now");
    out.sample("sms_gateway_mqtt_devices_online", {}, std::uint64_t{mqtt.devices_online});
  }

  if (!snapshot.rtu_slaves.empty()) {
    // Upstream Modbus RTU ports (docs/RTU_PANELS.md "Metrics"), labelled by device.
    struct RtuSlaveFamily {
      std::string_view name;
      MetricType type;
      std::string_view help;
      std::uint64_t RtuSlaveStats::*value;
    };
    static constexpr std::array<RtuSlaveFamily, 9> kRtuSlaveFamilies{{
        {"sms_gateway_rtu_slave_requests_total", MetricType::Counter,
         "Requests received on an upstream RTU port for a unit it serves (broadcasts included)",
         &RtuSlaveStats::requests},
        {"sms_gateway_rtu_slave_answers_total", MetricType::Counter, "Answer frames sent on an upstream RTU port",
         &RtuSlaveStats::answers},
        {"sms_gateway_rtu_slave_broadcasts_total", MetricType::Counter,
         "Broadcast writes (unit 0) carried out, never answered", &RtuSlaveStats::broadcasts},
        {"sms_gateway_rtu_slave_crc_errors_total", MetricType::Counter, "Frames dropped for a wrong CRC",
         &RtuSlaveStats::crc_errors},
        {"sms_gateway_rtu_slave_dropped_frames_total", MetricType::Counter,
         "Frames dropped: a silence over t1.5 inside, under 4 or over 256 bytes, a broadcast read, a queue overrun",
         &RtuSlaveStats::dropped_frames},
        {"sms_gateway_rtu_slave_echoes_total", MetricType::Counter,
         "Frames dropped as the adapter's echo of an answer (identical to it, within the port's echo window)",
         &RtuSlaveStats::echoes},
        {"sms_gateway_rtu_slave_silent_units_total", MetricType::Counter,
         "Valid frames for a unit the port does not serve, left unanswered", &RtuSlaveStats::silent_units},
        {"sms_gateway_rtu_slave_role_refusals_total", MetricType::Counter,
         "Requests the port's role may not make (answered 0x01 or 0x02)", &RtuSlaveStats::role_refusals},
        {"sms_gateway_rtu_slave_port_lost_total", MetricType::Counter, "Times the port's device failed or vanished",
         &RtuSlaveStats::port_lost},
    }};
    out.family("sms_gateway_rtu_slave_up", MetricType::Gauge, "1 while the upstream RTU port's device is open");
    for (const auto& port : snapshot.rtu_slaves) {
      out.sample("sms_gateway_rtu_slave_up", {{"device", port.device}}, std::uint64_t{port.open ? 1u : 0u});
    }
    for (const auto& family : kRtuSlaveFamilies) {
      out.family(family.name, family.type, family.help);
      for (const auto& port : snapshot.rtu_slaves)
        out.sample(family.name, {{"device", port.device}}, port.*family.value);
    }
  }

  if (snapshot.console_logins) {
    const ConsoleLoginMetrics& logins = *snapshot.console_logins;
    constexpr std::string_view kLogins = "sms_gateway_console_logins_total";
    out.family(kLogins, MetricType::Counter,
               "Password logins of the browser console by result: ok, failed (wrong password or unknown user), "
               "throttled (refused at once: the address or user waits after failed logins), busy (refused at "
               "once: the queue of password checks was full)");
    out.sample(kLogins, {{"result", "ok"}}, logins.ok);
    out.sample(kLogins, {{"result", "failed"}}, logins.failed);
    out.sample(kLogins, {{"result", "throttled"}}, logins.throttled);
    out.sample(kLogins, {{"result", "busy"}}, logins.busy);
    constexpr std::string_view kWaiting = "sms_gateway_console_login_waits";
    out.family(kWaiting, MetricType::Gauge,
               "Source addresses and user names whose browser console logins wait now after failed logins");
    out.sample(kWaiting, {{"scope", "address"}}, logins.addresses_waiting);
    out.sample(kWaiting, {{"scope", "user"}}, logins.users_waiting);
  }

  out.family("sms_gateway_estop_latched", MetricType::Gauge,
             "1 while the e-stop (gateway unit coil 1) is latched: motion writes refused on every bus");
  out.sample("sms_gateway_estop_latched", {}, std::uint64_t{snapshot.estop_latched ? 1u : 0u});
  out.family("sms_gateway_estops_total", MetricType::Counter, "Times a client latched the e-stop");
  out.sample("sms_gateway_estops_total", {}, snapshot.estops);
  out.family("sms_gateway_safety_state_not_persisted", MetricType::Gauge,
             "1 while the safety state (e-stop latch, tripped watchdogs, owed stops) could not be saved to state_dir: "
             "a restart now would forget it");
  out.sample("sms_gateway_safety_state_not_persisted", {},
             std::uint64_t{snapshot.safety_state_not_persisted ? 1u : 0u});

  render_requests(out, snapshot.traffic);
  constexpr std::string_view kResponses = "sms_gateway_modbus_responses_total";
  out.family(kResponses, MetricType::Counter, "Modbus TCP answers sent, normal and exception");
  out.sample(kResponses, {}, snapshot.traffic.responses);
  render_exceptions(out, snapshot.traffic);
  return out.take();
}

Health health_of(const MetricsSnapshot& snapshot) {
  Health health;
  for (const auto& bus : snapshot.buses) {
    if (bus.up) continue;
    if (!health.reason.empty()) health.reason += "; ";
    health.reason += "bus " + bus.name + " is down";
  }
  if (snapshot.safety_state_not_persisted) {
    if (!health.reason.empty()) health.reason += "; ";
    health.reason += "safety state not persisted: " + snapshot.safety_state_problem;
  }
  health.ok = health.reason.empty();
  if (health.ok) health.reason = "ok";
  return health;
}

}  // namespace sms::gateway
