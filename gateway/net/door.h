#pragma once
// The front door every TCP listener of the gateway shares (Modbus TCP, Modbus/TCP Security, the
// console over HTTP or HTTPS, /metrics): who may come in, who makes room, who is closed for
// taking too long, and the counts /metrics shows per listener. Each listener only configures it
// (DoorSettings) and tells it what happened to a connection; the rules live here once.
//
// A connection is *waiting* from its accept until it is *trusted*: on Modbus TCP and /metrics
// once its first complete request came, on the TLS listener once its handshake is done, on the
// console once a request of it carries a principal with a role (a login, a certificate, the
// loopback user). Waiting connections have a budget of their own, on the listener and per client
// address, so they can never take the place of a trusted one:
//   - on accept, when the client's address, or the listener, has the most waiting connections it
//     may have, the oldest of them is closed to make room (a silent one first: one that has sent
//     nothing yet) — a connection that sits there cannot keep a newer client out, the newcomer
//     only has to finish its first request before that many newer ones arrive;
//   - a waiting connection that has not completed its first request (or handshake) within the
//     first-request timeout is closed;
//   - a connection is refused at accept while the trusted budget (max_connections) is full, and
//     one that becomes trusted over it is closed (both counted as `full`).
//
//   Door door(io, {.listener = "console", .log_name = "console", ...});
//   auto ticket = door.admit(peer_address, session);   // nullopt: refused; close the socket
//   door.heard(*ticket);                               // first complete request: no deadline any more
//   if (!door.trust(*ticket)) close();                 // authenticated: counts as served
//   door.leave(*ticket);                               // closed, whoever closed it
//
// Threading: everything but stats() on the thread that runs `io` (one thread per listener).
// Asio stays out of this header.
#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

namespace boost::asio {
class io_context;
}

namespace sms::gateway {

// "60 s", "150 ms": for log lines.
std::string duration_text(std::chrono::milliseconds duration);

// A connection as the door sees it; the listener's session implements it.
class DoorGuest {
 public:
  // Close now: evicted to make room, or past the first-request deadline. The session then calls
  // Door::leave() as for any close.
  virtual void close_by_door() = 0;
  // Nothing came from the client yet (such connections make room first).
  virtual bool silent() const = 0;
  // "10.0.0.7:51234", for the log.
  virtual const std::string& peer() const = 0;

 protected:
  ~DoorGuest() = default;
};

// Why the door closed a connection, as /metrics labels it
// (sms_gateway_listener_closed_total{reason=...}).
enum class DoorClose : std::uint8_t { Full, Evicted, Deadline, Allow };
inline constexpr std::array<std::string_view, 4> kDoorCloseNames{"full", "evicted", "deadline", "allow"};

// The numbers of a door.
struct DoorLimits {
  std::size_t max_served = 32;
  std::size_t max_waiting = 16;
  std::size_t max_waiting_per_address = 4;
  std::chrono::milliseconds first_request_timeout{std::chrono::seconds{10}};  // 0: no deadline
};

// Where each of DoorLimits is set, for the log lines that name a limit reached.
struct DoorLimitNames {
  std::string max_served;
  std::string max_waiting;
  std::string max_waiting_per_address;
  std::string first_request_timeout;
};
// The names of limits fixed in code, e.g. "the console's connection limit".
DoorLimitNames fixed_limit_names(std::string_view whose);

struct DoorSettings {
  std::string listener;  // the /metrics label: "plain", "tls", "console", "metrics"
  std::string log_name;  // the log lines' prefix: "modbus tcp", "console"
  // What a connection must complete to stop waiting: "complete HTTP request".
  std::string first_request = "complete first request";
  DoorLimits limits;
  DoorLimitNames limit_names;
  // Told of each connection the door itself closes (Evicted, Deadline), after the count and the
  // log line: the TLS listener counts them as handshake results too. May be empty.
  std::function<void(DoorClose)> on_close;
};

struct DoorStats {
  std::size_t waiting = 0;  // connections open and not trusted yet
  std::size_t served = 0;   // trusted connections open
  std::uint64_t accepted = 0;
  std::array<std::uint64_t, kDoorCloseNames.size()> closed{};  // by DoorClose

  std::uint64_t closed_for(DoorClose why) const { return closed[static_cast<std::size_t>(why)]; }
};

class Door {
 public:
  using Ticket = std::uint64_t;

  Door(boost::asio::io_context& io, DoorSettings settings);
  ~Door();
  Door(const Door&) = delete;
  Door& operator=(const Door&) = delete;

  // A connection accepted from `address` (no port). nullopt when the trusted budget is full (counted;
  // logged once per episode): the caller closes the socket without an answer. May close older
  // waiting connections first (DoorGuest::close_by_door) to make room.
  std::optional<Ticket> admit(const std::string& address, std::weak_ptr<DoorGuest> guest);
  // The connection's first complete request (or handshake) came: no deadline any more. It stays
  // waiting, and may still make room for others, until trusted.
  void heard(Ticket ticket);
  // The connection has a right to be served (see the top). false when the trusted budget is
  // full: counted and logged, and the caller closes it.
  bool trust(Ticket ticket);
  bool trusted(Ticket ticket) const;
  // The connection closed, for whatever reason. Unknown tickets are ignored.
  void leave(Ticket ticket);
  // A connection closed at accept for the listener's allow-list (counted here with the others).
  void count_denied();
  // No more deadlines; the guests still open are the listener's to close.
  void close();

  const DoorSettings& settings() const;
  // "at most 32 connections served; at most 16 waiting for a complete HTTP request, 4 per client
  // address, each within 5 s"
  std::string describe() const;
  // Any thread.
  DoorStats stats() const;

  struct State;

 private:
  std::shared_ptr<State> state_;
};

}  // namespace sms::gateway
