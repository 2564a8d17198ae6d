#pragma once
// Every URL the console answers, as one table (console_routes.cpp `kRoutes`): method, path
// pattern, the role it needs, and what answers it — an embedded page, a JSON handler, or a
// WebSocket stream. The connection (console_http.cpp) does the HTTP and admission
// (console_admission.cpp) the access rules and the CSRF check before a handler runs; handlers
// see only the gateway through `Services`.
//
// Adding a page with its live data is one entry per URL and one function each, e.g. a bus page:
//   {"GET", "/bus/{name}/thing", Role::Read, RouteKind::Page, "thing.html"},
//   {"GET", "/ws/bus/{name}/thing", Role::Read, RouteKind::Socket, {}, nullptr, make_thing_stream},
// with web/thing.html (+ .js) listed in gateway/console/CMakeLists.txt (embedded) — docs/CONSOLE.md
// "Adding a page".
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "config/config.h"
#include "gateway/bus/wire_monitor.h"
#include "gateway/console/console_access.h"
#include "gateway/console/console_jog.h"
#include "gateway/console/console_request.h"
#include "gateway/console/login_guard.h"
#include "gateway/observability/metrics.h"
#include "gateway/service/access_gate.h"
#include "gateway/units/unit_router.h"
#include "protocol/expected.h"
#include "protocol/packet.h"

namespace sms::gateway::console {

struct HttpAnswer {
  unsigned status = 200;
  std::string content_type = "application/json";
  std::string body;
  std::vector<std::pair<std::string, std::string>> headers;  // Set-Cookie, Location ...

  static HttpAnswer json(unsigned status, const nlohmann::json& body);
  // {"error": message}: every refusal says what is wrong and what to do.
  static HttpAnswer error(unsigned status, std::string message);
};

// The answer to a Modbus request the console made.
struct ModbusAnswer {
  protocol::Bytes pdu;         // the response PDU
  std::uint8_t exception = 0;  // 0: no exception
  std::string message;         // "0x04 server device failure: motion blocked ..." for the page
  bool role_refused = false;   // the role gate refused it (it never reached the router): HTTP 403
  bool ok() const { return exception == 0 && !pdu.empty(); }
};

// The gateway as handlers and streams see it. Console thread only.
class Commissioning;

class Services {
 public:
  virtual ~Services() = default;
  virtual const config::Config& config() const = 0;
  virtual const config::ConsoleConfig& settings() const = 0;
  virtual const UnitRouter& units() const = 0;
  // The overview's JSON, made at most once per push period whoever asks.
  virtual const nlohmann::json& overview() = 0;
  virtual SessionStore& sessions() = 0;
  // The commissioning jobs (console_commission.h).
  virtual Commissioning& commissioning() = 0;
  // The bus monitor of the bus named `bus` (docs/MONITOR.md); nullptr when no bus has that name.
  virtual std::shared_ptr<WireMonitor> monitor(std::string_view bus) const = 0;
  // Set-Cookie text for a session token (empty: clears the cookie).
  virtual std::string session_cookie(const std::string& token) const = 0;
  // A Modbus request made as `who`: first the role gate every way in passes (refused: an
  // exception answer without reaching the router), then the unit router on the gateway's io
  // thread, like any Modbus client. `done` runs on the console thread.
  virtual void modbus(const Principal& who, std::uint8_t unit, protocol::Bytes pdu,
                      std::function<void(ModbusAnswer)> done) = 0;
  // Whether that gate refuses `pdu` from `who` (a refusal is logged and counted as one): asked
  // before a sequence of requests whose first would not be the one refused (an EEPROM write's
  // unlock), so the refusal names the write the user asked for.
  virtual std::optional<GateRefusal> refusal(const Principal& who, std::uint8_t unit,
                                             std::span<const std::uint8_t> pdu) = 0;
  // Bus `bus`'s motion stops now (SafetySupervisor::motion_stops): what a hold-to-run move checks.
  virtual MotionStops motion_stops(std::size_t bus) const = 0;
  // The servo's `hold`, as every safe stop writes it (SafetySupervisor::hold_servo), for a
  // hold-to-run move that ends. `done(ok)` runs on the console thread.
  virtual void hold_servo(const Principal& who, const ServoUnit& unit, std::function<void(bool ok)> done) = 0;
  // A write of the hold-to-run move `session`: as modbus(), and on the io thread, right before the
  // router admits it, the session is checked again; one a stop has ended gets 0x04 and nothing is
  // written (a latch and its reset between two looks of the console thread cannot let it through).
  virtual void jog_modbus(const Principal& who, std::uint8_t unit, protocol::Bytes pdu, const JogSession& session,
                          std::function<void(ModbusAnswer)> done) = 0;
  // A password login from `address` (login_guard.h): the backoff first, then the check on the
  // login worker, never on this thread. `done` runs on the console thread.
  virtual void login(std::string_view address, std::string user, std::string password,
                     std::function<void(LoginOutcome)> done) = 0;
};

// One HTTP request a JSON handler answers. `answer` may be called later (after Modbus answers),
// exactly once, on the console thread.
struct ApiCall {
  Services& services;
  PathParams params;
  std::string body;
  Principal who;
  std::optional<Session> session;
  bool peer_loopback = false;
  std::function<void(HttpAnswer)> answer;
  std::string peer_address;  // "192.168.10.7": logins are counted per address
};
using ApiHandler = void (*)(const std::shared_ptr<ApiCall>& call);

// One open WebSocket: what it pushes and what it does with a page's messages.
class Stream {
 public:
  using Send = std::function<void(std::string)>;
  virtual ~Stream() = default;
  // Every sample period (10 ms): look at the gateway (e.g. a new poll of the servo).
  virtual void sample(SteadyClock::time_point now) { (void)now; }
  // Every push period (100 ms): the batched message, or nullopt when there is nothing new.
  virtual std::optional<std::string> flush(SteadyClock::time_point now) = 0;
  // A text message from the page (at most ConsoleLimits::max_message_bytes).
  virtual void on_message(std::string_view text, const Send& send) { (void)text, (void)send; }
  // The page went away (tab closed, connection lost, server stopping).
  virtual void on_close() {}
};
using StreamFactory = Expected<std::unique_ptr<Stream>> (*)(Services& services, const PathParams& params,
                                                            const Principal& who);

// For a page whose URL names a thing (a unit, a bus): the API's refusal when there is no such
// thing (404 naming what exists), shown as a page (error_page) instead of an empty one.
using PageCheck = std::optional<HttpAnswer> (*)(Services& services, const PathParams& params);

enum class RouteKind : std::uint8_t {
  Page,    // an embedded file (`page`; empty: the {file} parameter, for /static/{file})
  Api,     // `api`, JSON
  Socket,  // a WebSocket upgrade; `socket` makes the stream
};

struct Route {
  std::string_view method;  // "GET" or "POST"
  std::string_view pattern;
  config::Role need = config::Role::Read;  // None: anyone (login page, static files)
  RouteKind kind = RouteKind::Page;
  std::string_view page = {};
  ApiHandler api = nullptr;
  StreamFactory socket = nullptr;
  bool csrf = true;             // POST only: needs the session's X-CSRF-Token (false: the login itself)
  PageCheck missing = nullptr;  // Page only: the refusal when the URL names nothing that exists
};

// An HTML page with the message of a JSON refusal ({"error": ...}) and its status, escaped.
HttpAnswer error_page(const HttpAnswer& refusal);

std::span<const Route> console_routes();

// The push and sample periods (docs/CONSOLE.md: pushed at most every 100 ms, batched).
inline constexpr std::chrono::milliseconds kPushPeriod{100};
inline constexpr std::chrono::milliseconds kSamplePeriod{10};
// A hold-to-run move stops when no heartbeat came for this long (the page sends one every 50 ms).
inline constexpr std::chrono::milliseconds kJogHeartbeatTimeout{150};
// While held, the move's goal is written again this often (it is the operator's presence: it
// feeds the bus watchdog like any carried-out write).
inline constexpr std::chrono::milliseconds kJogRefreshPeriod{250};

// A field write from the servo page, checked before anything is sent: the field by its name, the
// unit's `read_only`, the fields only commissioning changes, then the value check every way in
// shares (RegisterMap::check_write), worded as the Sparkplug node words it. The entry and the
// checked value, or the page's 400 answer ("...; nothing written").
struct CheckedFieldWrite {
  const modbus_map::RegisterEntry* entry = nullptr;
  modbus_map::CheckedWrite value;
};
Expected<CheckedFieldWrite, HttpAnswer> check_field_write(const ServoUnit& unit, std::string_view field,
                                                          std::int64_t value);

// The Modbus exception in a response PDU as text for a page, e.g. "exception 0x04 (server device
// failure): motion is blocked — the e-stop is latched or the watchdog tripped"; empty for none.
std::string exception_text(std::uint8_t exception);

}  // namespace sms::gateway::console
