#pragma once
// The browser commissioning console (docs/CONSOLE.md): HTTP/1.1 and WebSocket (Boost.Beast),
// HTTPS with the Modbus/TCP Security files when console.tls is set. It runs on its own thread
// and io_context, so a slow or hostile browser never delays a Modbus answer; it reads the
// gateway as /metrics does, and every write it makes is a Modbus PDU handed to the unit router
// on the gateway's io thread (through the same RolePolicy as Modbus/TCP Security), so the
// safety rules and the answers are exactly a Modbus client's.
//
//   ConsoleServer console(*config.console, ConsoleBackend{...});
//   console.start();   // throws std::runtime_error naming the address and what to do
//   ...
//   console.stop();
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_join.h"
#include "gateway/bus/wire_monitor.h"
#include "gateway/console/console_commission.h"
#include "gateway/console/login_guard.h"
#include "gateway/net/door.h"
#include "gateway/observability/metrics.h"
#include "gateway/service/request_handler.h"
#include "gateway/service/role_policy.h"
#include "gateway/units/safety.h"
#include "gateway/units/unit_router.h"

namespace sms::gateway::console {

// What the console needs of the running gateway; everything must outlive the server.
struct ConsoleBackend {
  const config::Config* config = nullptr;
  const UnitRouter* units = nullptr;         // servo units: register maps, engines (immutable after start)
  RequestHandler* router = nullptr;          // called on the gateway's io thread only
  PostFn post_to_router;                     // runs work on that thread
  std::function<MetricsSnapshot()> metrics;  // any thread (as /metrics calls it)
  // The bus monitor of the bus named so (docs/MONITOR.md), nullptr for no such bus; any thread.
  std::function<std::shared_ptr<WireMonitor>(std::string_view bus)> monitor;
  BusLending lending;  // empty functions: no bus can be stopped from the console (tests)
  // The safety rules every hold-to-run move checks (console_jog.h), and the hold that ends one
  // (SafetySupervisor::hold_servo); required.
  SafetySupervisor* safety = nullptr;
  // The role rights every request passes before the router (the gateway's one RolePolicy); required.
  const RolePolicy* policy = nullptr;
};

// The console's door (gateway/net/door.h) and its requests' bounds.
struct ConsoleLimits {
  // Connections served: signed in (a login, a certificate with a role, the loopback user). Those
  // not signed in yet have a budget apart, per client address too, and must send a complete
  // request within the deadline: they can never keep an operator (and the e-stop) out. A browser
  // opens up to 6 connections to one host while it loads a page, so one address may have 8
  // waiting: a page load on a busy edge box never evicts its own connections.
  DoorLimits door{.max_served = 32,
                  .max_waiting = 16,
                  .max_waiting_per_address = 8,
                  .first_request_timeout = std::chrono::seconds{5}};
  std::size_t max_header_bytes = 8192;
  std::size_t max_body_bytes = 16384;
  std::size_t max_message_bytes = 4096;  // one WebSocket message from a page
  std::chrono::milliseconds request_timeout{std::chrono::seconds{10}};
};

class ConsoleServer {
 public:
  ConsoleServer(config::ConsoleConfig settings, ConsoleBackend backend, ConsoleLimits limits = {});
  ~ConsoleServer();  // stop()
  ConsoleServer(const ConsoleServer&) = delete;
  ConsoleServer& operator=(const ConsoleServer&) = delete;

  // Binds and listens on the calling thread (errors surface here), then serves on its own.
  void start();
  // Closes every connection; a hold-to-run move still running is stopped first. Idempotent.
  void stop();
  std::uint16_t port() const;
  // Password logins so far (login_guard.h); any thread.
  LoginStats login_stats() const;
  // "http://127.0.0.1:8080/" (https with tls).
  std::string url() const;
  // The listener's door (sms_gateway_listener_* in /metrics); any thread.
  DoorStats door_stats() const;

  class Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway::console
