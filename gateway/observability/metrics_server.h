#pragma once
// The HTTP endpoint for monitoring (`--metrics HOST:PORT`, logging.metrics_listen):
//
//   GET /metrics   200, Prometheus text format 0.0.4 (metrics.h)
//   GET /healthz   200 "ok" when every bus is up, 503 naming the buses that are down
//   HEAD on both   the same status and headers without a body
//   other methods on those paths 405; any other path 404
//
// HTTP/1.1 with keep-alive (Boost.Beast). It runs on its own thread and io_context, so a slow
// or hostile HTTP client can never delay a Modbus answer; it reads the gateway only through
// the snapshot function, which takes no lock a bus holds while it waits for a servo. Each
// connection must send a whole request within `request_timeout` (also the keep-alive idle
// limit), requests are bounded in size, and the listener's door (gateway/net/door.h) keeps
// connections that never finish a request from taking a scraper's place. There is no authentication: bind it to a local
// or management address. Asio and Beast stay out of this header.
//
//   MetricsServer server({.listen = *config.logging.metrics_listen},
//                        [&] { return collect_metrics(...); });
//   server.start();    // throws std::runtime_error naming the address and what to do
//   ...
//   server.stop();
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>

#include "config/config.h"
#include "gateway/net/door.h"
#include "gateway/observability/metrics.h"

namespace sms::gateway {

struct MetricsServerOptions {
  config::HostPort listen{"127.0.0.1", 9102};  // port 0: any free port (tests); port() says which
  // The listener's door (gateway/net/door.h): connections served (past a complete request), and
  // those still waiting for one, apart, per client address too, each within the deadline.
  DoorLimits door{.max_served = 8,
                  .max_waiting = 8,
                  .max_waiting_per_address = 4,
                  .first_request_timeout = std::chrono::seconds{5}};
  std::chrono::milliseconds request_timeout{std::chrono::seconds{10}};  // keep-alive idle limit
  std::size_t max_request_bytes = 8192;  // request line and headers; a request body is refused
};

class MetricsServer {
 public:
  // Called on the server's thread for every /metrics and /healthz request.
  using SnapshotFn = std::function<MetricsSnapshot()>;

  MetricsServer(MetricsServerOptions options, SnapshotFn snapshot);
  ~MetricsServer();  // stop()
  MetricsServer(const MetricsServer&) = delete;
  MetricsServer& operator=(const MetricsServer&) = delete;

  // Binds and listens on the calling thread (so errors surface here), then serves on its own.
  void start();
  // Closes the listener and every connection, joins the thread. Idempotent.
  void stop();
  std::uint16_t port() const;

  class Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
