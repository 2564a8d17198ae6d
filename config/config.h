#pragma once
// The gateway's configuration as plain values: what config/load.h produces from a YAML file
// after validation. Every key, its default and its meaning: config/README.md.
// No yaml-cpp here; the loader keeps it to itself.
#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"
#include "modbus_map/motion.h"
#include "protocol/bus_protocol.h"
#include "protocol/expected.h"

namespace sms::config {

// "HOST:PORT"; an IPv6 host is written in brackets: "[::1]:502".
struct HostPort {
  std::string host;
  std::uint16_t port = 0;

  std::string to_string() const;
  bool operator==(const HostPort&) const = default;
};
// Error text says what is wrong with `text` (no location; callers add theirs).
Expected<HostPort> parse_host_port(std::string_view text);

// An IPv4 or IPv6 network in CIDR form: "192.168.10.0/24", "fd00:1::/64"; a bare address is
// one host ("10.0.0.7" = /32, "::1" = /128). Host bits below the prefix are zero.
struct IpNetwork {
  enum class Family : std::uint8_t { V4, V6 };
  Family family = Family::V4;
  std::array<std::uint8_t, 16> address{};  // network byte order; IPv4 uses the first 4 bytes
  std::uint8_t prefix_length = 32;

  std::string to_string() const;  // "192.168.10.0/24", "fd00:1::/64"
  bool operator==(const IpNetwork&) const = default;
};
// Error text says what is wrong with `text` and shows the valid form (no location).
Expected<IpNetwork> parse_ip_network(std::string_view text);

// Limits shared by the YAML loader and the environment overlay (config/env.h).
inline constexpr std::size_t kMaxConnectionsLimit = 4096;
inline constexpr std::int64_t kMaxIdleTimeoutSeconds = 86400;

// Modbus/TCP Security (docs/SECURITY.md): what a client certificate may do.
// Read: reads only (an HMI). Operate: also writes to RAM fields (motion, torque, the gateway
// unit's coils and sync groups). Engineer: everything, EEPROM fields, ID and baud rate,
// calibration included. None: no rights; a connection whose certificate gets no role is closed.
enum class Role : std::uint8_t { None, Read, Operate, Engineer };

// One entry of modbus_tcp.tls.roles: a certificate's subject CN or subjectAltName (DNS name,
// e-mail, URI or IP address as text) and the role it gets when the certificate carries no
// Modbus.org role extension (OID 1.3.6.1.4.1.50316.802.1).
struct TlsRoleMapping {
  std::string name;
  Role role = Role::None;

  bool operator==(const TlsRoleMapping&) const = default;
};

// The Modbus/TCP Security listener: TLS 1.2/1.3 with client certificates (mutual
// authentication). The files are PEM; SIGHUP reloads them.
struct TlsConfig {
  HostPort listen;
  std::string certificate;            // the gateway's certificate (chain), PEM
  std::string private_key;            // its key, PEM, unencrypted
  std::string ca;                     // CA certificates client certificates must chain to, PEM
  std::vector<TlsRoleMapping> roles;  // in file order; names unique
  Role default_role = Role::None;     // for a certificate with no extension and no mapping
  // Role extension texts of other schemes ("Operator") and the role each gives; an extension
  // naming neither a role nor an entry here falls back to `roles` and `default_role`.
  std::vector<TlsRoleMapping> role_names;
  // Connections still in the TLS handshake (unauthenticated) have their own budget, apart from
  // max_connections (which counts authenticated ones): at most `max_handshakes` on the listener
  // and `max_handshakes_per_address` from one client address; past either, the oldest such
  // connection is closed for the new one. A handshake not done in `handshake_timeout` is closed.
  std::chrono::milliseconds handshake_timeout{3000};
  std::size_t max_handshakes = 16;
  std::size_t max_handshakes_per_address = 4;

  bool operator==(const TlsConfig&) const = default;
};

struct ModbusTcpConfig {
  // Local only by default, on an unprivileged port; a plant config says e.g. 0.0.0.0:502.
  HostPort listen{"127.0.0.1", 5020};
  // false: no plain (unauthenticated) Modbus TCP listener; then `tls` is required.
  bool plain = true;
  std::optional<TlsConfig> tls;      // the Modbus/TCP Security listener; empty: none
  std::size_t max_connections = 32;  // served: past the first complete request
  // Connections still waiting for their first complete request, apart from max_connections: at
  // most `max_waiting`, `max_waiting_per_address` from one client address; past either the
  // oldest such connection is closed for the new one; one without a complete request within
  // `first_request_timeout` is closed (gateway/net/door.h).
  std::size_t max_waiting = 16;
  std::size_t max_waiting_per_address = 8;
  std::chrono::milliseconds first_request_timeout{60000};
  std::chrono::seconds idle_timeout{60};  // 0: never close an idle client
  std::uint8_t gateway_unit_id = 255;     // the gateway's own unit (docs/PLC_GUIDE.md)
  // Client requests one bus may have waiting; past it a request is answered 0x06 (busy).
  std::size_t request_queue_depth = 64;
  // Client addresses allowed to connect; empty: every client. Modbus has no authentication, so
  // this and the bind address are the gateway's access control (docs/SECURITY.md).
  std::vector<IpNetwork> allow;

  bool operator==(const ModbusTcpConfig&) const = default;
};

enum class Parity : std::uint8_t { None, Even, Odd };
// libmodbus's RTS control for RS-485 direction switching (modbus_rtu_set_rts).
enum class RtsMode : std::uint8_t { None, Up, Down };

// A block of bus addresses: bytes on packet buses, registers on modbus-rtu buses.
struct AddressRange {
  std::uint16_t start = 0;
  std::uint16_t count = 0;

  bool operator==(const AddressRange&) const = default;
};

// What the poll cycle reads from each servo of a bus. Both empty: the table's feedback block
// (resolved by the gateway from modbus_map). Never both set.
struct PollSelection {
  std::vector<std::string> fields;    // field names, each present in every table on the bus
  std::optional<AddressRange> range;  // fits every table on the bus

  bool table_default() const { return fields.empty() && !range; }
  bool operator==(const PollSelection&) const = default;
};

// The silence the RTU master keeps after the last byte on the wire before it sends the next
// frame (Modbus over serial line v1.02 §2.5.1.1: 3.5 characters, a fixed 1.75 ms above 19200
// bit/s). Slaves that time their frames by 3.5 characters take the shorter gap at high rates.
struct FrameGap {
  enum class Kind : std::uint8_t { Spec, Characters, Fixed };
  Kind kind = Kind::Spec;              // Spec: 3.5 characters, 1.75 ms above 19200 bit/s
  std::chrono::microseconds fixed{0};  // Fixed only

  std::string to_string() const;  // "spec", "3.5chars", "250us"
  bool operator==(const FrameGap&) const = default;
};
// "spec", "3.5chars" or "<N>us" (0..1000000); the error says what is wrong and the valid forms.
Expected<FrameGap> parse_frame_gap(std::string_view text);

// Line settings only a modbus-rtu bus uses (libmodbus).
struct ModbusRtuOptions {
  bool rs485 = false;  // MODBUS_RTU_RS485 serial mode (TIOCSRS485)
  RtsMode rts = RtsMode::None;
  std::optional<std::chrono::microseconds> rts_delay;  // empty: libmodbus's one character time
  std::chrono::milliseconds byte_timeout{50};          // longest silence inside one reply
  FrameGap frame_gap;                                  // between frames, from the last byte on the wire

  bool operator==(const ModbusRtuOptions&) const = default;
};

// Motion safety (docs/PLC_GUIDE.md "Safety", docs/DECISIONS.md "Safety").
// What feeds a bus's watchdog: any Modbus write to a unit on the bus (servo, passthrough, a
// sync group member, its heartbeat register), or only a changed value in its heartbeat
// register (gateway unit holding register 1000 + bus index), as drives count a PLC's toggle.
enum class WatchdogFeed : std::uint8_t { AnyWrite, HeartbeatRegister };
// What the gateway does to a bus's servos when it starts: leave them as found, hold where they
// are, or switch their torque off.
enum class StartAction : std::uint8_t { Keep, Hold, TorqueOff };

inline constexpr std::int64_t kMinWatchdogTimeoutMs = 10;
inline constexpr std::int64_t kMaxWatchdogTimeoutMs = 600000;
// Gateway unit holding register of bus n's heartbeat (feed: heartbeat_register).
inline constexpr std::uint16_t kHeartbeatRegisterBase = 1000;

struct WatchdogConfig {
  std::chrono::milliseconds timeout{200};
  WatchdogFeed feed = WatchdogFeed::AnyWrite;
  // Overrides every servo's safe_stop for a trip of this watchdog; empty: each servo's own.
  std::optional<modbus_map::StopAction> action;

  bool operator==(const WatchdogConfig&) const = default;
};

struct BusConfig;
// The longest one client transaction can hold the bus: a fence read (sent first when its servo
// still owes late answers that could look like its answer, docs/DECISIONS.md "Late answers") and
// the request, each with every attempt, each attempt its reply allowance plus the wire time of
// the longest request and answer (256 bytes each way) at the bus's rate and framing. A watchdog
// must be longer (a trip's stop waits for the transaction on the wire).
std::chrono::milliseconds worst_transaction(const BusConfig& bus);

// d55d motors stop by themselves after 500 ms without an instruction (their heartbeat,
// docs/PROTOCOL.md §2.3 address 17). The gateway's polls and probes are instructions: an offline
// d55d motor is probed at least every kD55dKeepAlive whatever offline_probe_period_ms says, so the
// gateway's own silence never fires it (docs/PLC_GUIDE.md "d55d heartbeat").
inline constexpr std::chrono::milliseconds kD55dHeartbeat{500};
inline constexpr std::chrono::milliseconds kD55dKeepAlive{200};
// How often an offline servo of `bus` is probed: offline_probe_period_ms, at most kD55dKeepAlive on d55d.
std::chrono::milliseconds effective_probe_period(const BusConfig& bus);
// The longest an online d55d motor of `bus` can go without an instruction while the gateway runs:
// a poll period, then one worst transaction to another servo before its own poll; nullopt on
// other protocols. An offline one waits for its probe instead (effective_probe_period).
std::optional<std::chrono::milliseconds> d55d_instruction_gap(const BusConfig& bus);

struct BusConfig {
  std::string name;
  std::string device;  // /dev/ttyUSB0, /dev/serial/by-id/..., a pty path
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  std::uint32_t baud = 0;      // bits per second, a rate of the protocol's table (docs/PROTOCOL.md §3)
  std::uint8_t baud_code = 0;  // that rate's code in the protocol's table
  Parity parity = Parity::None;
  std::uint8_t stop_bits = 1;  // 1 or 2
  // Wait for a reply beyond its wire time: return delay plus adapter latency (docs/PROTOCOL.md §5).
  std::chrono::milliseconds response_timeout{20};
  unsigned retries = 2;                                  // attempts after the first one
  std::chrono::milliseconds poll_period{20};             // start of one poll cycle to the next; 0 = back to back
  std::chrono::milliseconds offline_probe_period{1000};  // an offline servo is asked once per period
  std::chrono::milliseconds reopen_period{1000};         // a missing or lost port is retried this often
  PollSelection poll;
  ModbusRtuOptions modbus_rtu;             // used only when protocol is ModbusRtu
  std::optional<WatchdogConfig> watchdog;  // empty: no watchdog on this bus
  StartAction on_start = StartAction::Keep;
  // What SIGTERM / SIGINT do to the bus's servos before the gateway lets go of the port.
  modbus_map::StopAction on_stop = modbus_map::StopAction::Hold;
  // The ramp every hold of this bus brakes at, in counts of the servos' ramp fields; empty: the
  // fastest each servo has (docs/SAFETY.md "Stop distance"). A servo's own overrides it.
  std::optional<std::int32_t> stop_deceleration;

  bool operator==(const BusConfig&) const = default;
};

// Which register map a servo unit shows a Modbus client (docs/PLC_GUIDE.md "Two register profiles").
enum class Profile : std::uint8_t { Native, Smsmb };

struct ServoConfig {
  std::uint8_t unit_id = 0;   // Modbus unit 1..247
  std::string bus;            // a BusConfig::name
  std::size_t bus_index = 0;  // that bus's index in Config::buses
  std::uint8_t servo_id = 0;  // 0..253 on packet buses, 1..247 on modbus-rtu
  // Empty: passthrough (modbus-rtu buses only): Modbus PDUs for this unit are forwarded to the
  // slave unchanged.
  std::optional<modbus_map::TableId> table;
  // Smsmb only for sts/sms1; an smsmb table's native map already is the SMSMB map, so it is
  // stored as Native.
  Profile profile = Profile::Native;
  std::optional<modbus_map::ByteOrder> byte_order;  // overrides the table's (docs/PROTOCOL.md §2.2)
  // The servo's response level as set in it, so the gateway knows whether writes are
  // answered; empty: the gateway finds out from the servo.
  std::optional<std::uint8_t> response_level;
  bool read_only = false;  // client writes refused (0x02)
  std::string name;        // label for logs and dumps, may be empty
  // What a watchdog trip or the e-stop does to this servo; empty: the table's default
  // (modbus_map::motion_spec(table).default_stop). Passthrough units are never stopped.
  std::optional<modbus_map::StopAction> safe_stop;
  // The ramp its hold brakes at (counts of the table's stop ramp fields); empty: the bus's, else
  // the fastest the servo has (modbus_map::MotionSpec::stop_ramp).
  std::optional<std::int32_t> stop_deceleration;
  // Set when an earlier unit already shows the same servo (bus, id): the unit id of that first
  // one. Such a second view (an HMI's read-only unit) is served like any unit, but the servo is
  // polled, counted and stopped once, as the first unit. At most one unit of a servo is
  // writable; the units of one servo agree on table, byte_order, response_level and safe_stop.
  std::optional<std::uint8_t> view_of;

  bool passthrough() const { return !table.has_value(); }
  bool operator==(const ServoConfig&) const = default;
};

// The byte order the gateway uses for a table servo: the override, else the table's default.
// Passthrough servos: HighFirst (Modbus).
modbus_map::ByteOrder effective_byte_order(const ServoConfig& servo);

// A block of holding registers on the gateway unit; one FC16 write of it becomes one SYNC WRITE
// frame per bus (docs/PLC_GUIDE.md "The gateway unit").
struct SyncGroupConfig {
  std::string name;
  std::string field;                  // a writable field of every member's table
  std::vector<std::uint8_t> members;  // unit IDs, register i of the block is members[i]
  std::uint16_t holding_register_start = 0;
  // Timed moves (docs/PLC_GUIDE.md "Timed group moves"): the register after the members' holds
  // the move time in ms; the group's field must be every member's goal position.
  bool move_time = false;
  // A move time some axis cannot make is stretched to the slowest axis instead of refused.
  bool stretch = false;

  std::uint16_t member_count() const { return static_cast<std::uint16_t>(members.size()); }
  // The holding registers of the block: the members, then the move time when the group has one.
  std::uint16_t register_count() const { return static_cast<std::uint16_t>(members.size() + (move_time ? 1 : 0)); }
  bool operator==(const SyncGroupConfig&) const = default;
};

enum class LogLevel : std::uint8_t { Trace, Debug, Info, Warn, Error, Critical, Off };
// Plain text lines for people, or one JSON object per line for log collectors.
enum class LogFormat : std::uint8_t { Plain, Json };

struct LoggingConfig {
  LogLevel level = LogLevel::Info;
  LogFormat format = LogFormat::Plain;
  std::optional<HostPort> metrics_listen;  // Prometheus-style metrics endpoint, off when empty

  bool operator==(const LoggingConfig&) const = default;
};

// MQTT Sparkplug B northbound (docs/MQTT.md): the gateway is one Sparkplug edge
// node on an existing broker; every table servo is a device.
struct MqttTlsConfig {
  std::string ca;           // CA certificates the broker's certificate must chain to, PEM
  std::string certificate;  // the gateway's client certificate, PEM; empty: none
  std::string private_key;  // its key, PEM, unencrypted; given with `certificate`

  bool operator==(const MqttTlsConfig&) const = default;
};

// Field deadband of DDATA: a change smaller than `deadband` (in register units) is not sent.
struct MqttDeadband {
  std::string field;
  std::uint32_t deadband = 0;

  bool operator==(const MqttDeadband&) const = default;
};

struct MqttConfig {
  HostPort broker;            // the broker's host:port (1883 plain, 8883 TLS by custom)
  std::string group_id;       // Sparkplug group ID
  std::string edge_node_id;   // Sparkplug edge node ID
  std::string client_id;      // MQTT client ID; empty: "sms-gateway-<edge_node_id>"
  std::string username;       // empty: none
  std::string password_file;  // the password's file (first line); empty: none
  std::optional<MqttTlsConfig> tls;
  std::chrono::seconds keepalive{30};
  // The rights of DCMD/NCMD writes (the Modbus/TCP Security roles): read refuses every write,
  // operate allows RAM fields and the e-stop, engineer everything.
  Role role = Role::Operate;
  std::chrono::milliseconds data_period{100};  // how often the poll cache is checked for changes
  std::chrono::seconds report_period{0};       // every metric again this often; 0: changes only
  std::vector<MqttDeadband> deadbands;         // in file order, fields unique
  std::chrono::milliseconds reconnect_min{500};
  std::chrono::milliseconds reconnect_max{30000};
  // The Sparkplug host application whose STATE gates the births (config/README.md
  // "primary_host_id"); empty: none, births follow the connection.
  std::string primary_host_id;

  bool operator==(const MqttConfig&) const = default;
};

// The Sparkplug device ID of a servo unit: its name, else "unit-<N>".
std::string sparkplug_device_id(const ServoConfig& servo);

// An upstream Modbus RTU port (docs/RTU_PANELS.md): the gateway is a Modbus RTU slave on this
// serial line, for PLCs and HMI panels that are RTU masters, answering through the same unit
// router as Modbus TCP.
// The rates an upstream port may run at: whatever the panel and its adapter use (termios2 sets any rate).
inline constexpr std::uint32_t kMinRtuSlaveBaud = 300;
inline constexpr std::uint32_t kMaxRtuSlaveBaud = 4000000;

// Whether the port's adapter hands back what the port sends (an RS-485 adapter that does not
// switch its receiver off while sending): which frame is taken for the echo of an answer
// (docs/RTU_PANELS.md "Echoing adapters").
enum class RtuEcho : std::uint8_t {
  Auto,  // an identical frame that comes before a master could have sent one (t3.5 + wire time)
  On,    // the adapter echoes: an identical frame up to 50 ms late (its latency timer) too
  Off,   // it does not: no frame is an echo
};

struct RtuSlaveConfig {
  std::string device;            // a tty (the panel's RS-485 adapter), never a bus's device
  std::uint32_t baud = 19200;    // the Modbus serial line spec's default rate
  Parity parity = Parity::Even;  // the spec's default (8E1)
  std::uint8_t stop_bits = 1;    // 1 or 2
  // rs485, rts, rts_delay and frame_gap as on a modbus-rtu bus (byte_timeout is not used): here
  // frame_gap is the port's t3.5, which ends a request and comes before each answer.
  ModbusRtuOptions line;
  std::vector<std::uint8_t> units;  // the units the port answers; empty: every configured unit and the gateway unit
  Role role = Role::Operate;        // the rights of its requests, as Modbus/TCP Security roles
  std::chrono::milliseconds reopen_period{1000};  // a missing or lost device is retried this often
  RtuEcho echo = RtuEcho::Auto;

  bool operator==(const RtuSlaveConfig&) const = default;
};

// One user of the browser console (docs/CONSOLE.md): the rights of a Modbus/TCP Security role,
// the password as libsodium's crypto_pwhash_str() text (`sms-gateway hash-password` makes it).
struct ConsoleUser {
  std::string name;
  Role role = Role::Read;
  std::string password_hash;  // "$argon2id$v=19$m=...": never the password itself

  bool operator==(const ConsoleUser&) const = default;
};

// The browser commissioning console (docs/CONSOLE.md): HTTP/1.1 and WebSocket on `listen`.
struct ConsoleConfig {
  HostPort listen{"127.0.0.1", 8080};
  bool tls = false;  // HTTPS with modbus_tcp.tls's certificate, key and CA (client certificates give roles)
  // HTTPS with the console's own certificate (chain) and unencrypted key, PEM, for password
  // logins across the network; independent of modbus_tcp.tls. Both empty: none; never with `tls`.
  std::string certificate;
  std::string key;
  // Password users on a non-loopback address over plain HTTP anyway (passwords in clear on the
  // network): accepted only when said so, with a warning at every start.
  bool insecure_http = false;
  std::vector<ConsoleUser> users;                  // in file order; names unique
  std::chrono::seconds session_timeout{8 * 3600};  // a login lasts this long without use
  // `--simulate` only (never from a file): the local (loopback) user has every right, and when
  // the default port is taken (another demo, a test running several) any free port is used.
  bool local_user_has_every_right = false;
  bool any_port_if_taken = false;

  bool https() const { return tls || !certificate.empty(); }
  bool operator==(const ConsoleConfig&) const = default;
};

// Whether `host` names this machine only (127.0.0.0/8, ::1, localhost).
bool is_loopback_host(std::string_view host);
// Why the console cannot serve on its `listen` address as configured, or nullopt: a non-loopback
// address needs a way to know who asks (users or tls), and password users there need HTTPS
// (certificate and key, or tls) unless insecure_http says otherwise. The text says what to do.
std::optional<std::string> console_listen_problem(const ConsoleConfig& console);

struct Config {
  ModbusTcpConfig modbus_tcp;
  std::vector<BusConfig> buses;
  std::vector<ServoConfig> servos;
  std::vector<SyncGroupConfig> sync_groups;
  LoggingConfig logging;
  std::optional<MqttConfig> mqtt;  // empty: no MQTT
  // Where the gateway keeps what must survive a restart (the e-stop latch, tripped watchdogs,
  // the Sparkplug bdSeq): config/README.md "state_dir". Empty: $STATE_DIRECTORY (systemd's
  // StateDirectory=), else nothing is kept and the start says so.
  std::string state_dir;
  std::vector<RtuSlaveConfig> modbus_rtu_slave;  // upstream Modbus RTU ports; empty: none
  std::optional<ConsoleConfig> console;          // the browser console; empty: off

  bool operator==(const Config&) const = default;
};

// Where the state that must survive a restart is kept: `state_dir`, else the first entry of
// $STATE_DIRECTORY (systemd's StateDirectory=), else empty (nothing is kept).
std::string effective_state_dir(const Config& config);
// `--rtu-slave DEVICE[:BAUD[:PARITY]]` (parity even when not given); the error says what is
// wrong with `text` and shows the form.
Expected<RtuSlaveConfig> parse_rtu_slave_option(std::string_view text);
// Why `port` cannot be added to `config` (its device is a bus's or another port's), or nullopt.
std::optional<std::string> rtu_slave_conflict(const Config& config, const RtuSlaveConfig& port);

// Lookups; nullptr when absent.
const BusConfig* find_bus(const Config& config, std::string_view name);
const ServoConfig* find_unit(const Config& config, std::uint8_t unit_id);

// The spellings used in configuration files.
std::string_view to_string(Parity parity);
std::string_view to_string(RtsMode rts);
std::string_view to_string(Profile profile);
std::string_view to_string(LogLevel level);
std::string_view to_string(LogFormat format);
std::string_view to_string(modbus_map::ByteOrder order);  // "low-first", "high-first"
std::string_view to_string(WatchdogFeed feed);
std::string_view to_string(StartAction action);
std::string_view to_string(Role role);     // "none", "read", "operate", "engineer"
std::string_view to_string(RtuEcho echo);  // "auto", "on", "off"
std::optional<Role> role_from_name(std::string_view name);
// The safe stop a servo gets: its own, else its table's default; None for passthrough units.
modbus_map::StopAction effective_safe_stop(const ServoConfig& servo);
// The stop ramp of `servo`'s hold: its own stop_deceleration, else its bus's; empty: the fastest.
std::optional<std::int32_t> effective_stop_deceleration(const Config& config, const ServoConfig& servo);

}  // namespace sms::config
