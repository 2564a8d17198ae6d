#pragma once
// The Modbus TCP server: listens, lets connections in through the listener's door
// (gateway/net/door.h: a budget of served connections, one for those still waiting for their
// first request or TLS handshake, per client address too, their deadline), and runs one
// MbapSession per connection. Each session decodes
// MBAP frames, hands their PDUs to a RequestHandler one at a time and writes the answers back
// in request order with the transaction ids echoed, so pipelined requests are answered in
// order and a connection's writes reach the buses in the order they arrived.
//
// Threading: everything here runs on the io_context passed in, which must be run by a single
// thread (the sessions rely on it instead of strands). Asio stays out of this header.
#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "gateway/net/door.h"
#include "gateway/service/request_handler.h"
#include "protocol/packet.h"

namespace boost::asio {
class io_context;
}

namespace sms::gateway {

using protocol::Bytes;
class ModbusTrafficCounters;
class TlsService;

struct TcpServerOptions {
  std::string host = "127.0.0.1";
  std::uint16_t port = 502;  // 0: any free port (tests); port() says which
  // Connections served: past their first complete request (TLS: past the handshake). Those
  // still waiting for it have a budget apart (the door's), so they never take a served one's
  // place: plain from the three settings below, TLS from TlsConfig (max_handshakes, ...).
  std::size_t max_connections = 32;
  std::size_t max_waiting = 16;
  std::size_t max_waiting_per_address = 8;
  std::chrono::milliseconds first_request_timeout{std::chrono::seconds{60}};
  std::chrono::milliseconds idle_timeout{std::chrono::seconds{60}};  // 0: never close idle clients
  // Decoded requests a connection may have waiting behind the one being answered; past it the
  // session stops reading from the socket (TCP flow control pushes back on the client).
  std::size_t max_pipelined = 32;
  // Answer bytes a connection may have waiting to be written; past it the session starts no
  // new request until the client reads (so a client that never reads its answers cannot make
  // the gateway buffer without bound). A client that takes none of its answers for the idle
  // timeout is closed.
  std::size_t max_unsent_bytes = std::size_t{64} * 1024;
  // Client addresses allowed to connect (modbus_tcp.allow); empty: every client. Others are
  // closed on accept without a Modbus answer.
  std::vector<config::IpNetwork> allow;
  // Where requests by function and answers by exception code are counted (/metrics); may be null.
  // Must outlive the server.
  ModbusTrafficCounters* traffic = nullptr;
  // Modbus/TCP Security (gateway/modbus_tcp/tls.h): every connection first completes a TLS handshake with
  // a client certificate, and its requests go to the handler the service gives it (the role's
  // rights in front of the server's handler). nullptr: plain Modbus TCP. Must outlive the server.
  TlsService* tls = nullptr;
};

// The two listeners, as the `listener` label of /metrics names them (modbus_tcp.plain, .tls).
inline constexpr std::array<std::string_view, 2> kListenerNames{"plain", "tls"};

// Connections of one listener closed at once, by reason.
struct ConnectionRefusals {
  std::uint64_t max_connections = 0;
  std::uint64_t allow = 0;
};

struct TcpServerStats {
  std::size_t open_connections = 0;  // waiting ones (TLS: handshakes in progress) included
  std::uint64_t accepted = 0;
  std::uint64_t refused = 0;  // over the connection limit
  std::uint64_t denied = 0;   // not in the allow-list
  std::uint64_t requests = 0;
  std::uint64_t bad_headers = 0;  // connections closed for an MBAP header that is not Modbus
  std::uint64_t idle_closed = 0;
  // `refused` and `denied` by listener (kListenerNames index).
  std::array<ConnectionRefusals, kListenerNames.size()> refusals{};
};

class TcpServer {
 public:
  TcpServer(boost::asio::io_context& io, TcpServerOptions options, RequestHandler& handler);
  ~TcpServer();  // closes the listener and every connection at once
  TcpServer(const TcpServer&) = delete;
  TcpServer& operator=(const TcpServer&) = delete;

  // Binds and listens. Throws std::runtime_error naming the address and what to do when the
  // address cannot be resolved or bound (port in use, permission for ports below 1024).
  void start();
  // The bound port (the real one when the options asked for 0).
  std::uint16_t port() const;
  // Graceful stop: no new connections; each session finishes the request it is answering,
  // writes the answer, then closes (requests queued behind it were never answered and are
  // dropped). `done` runs on the io_context once every connection is closed.
  void shutdown(std::function<void()> done);
  // Closes every connection now, answered or not (the bus work in flight still completes).
  void close_all();

  // Thread-safe snapshots.
  TcpServerStats stats() const;
  DoorStats door_stats() const;            // the listener's door (sms_gateway_listener_* in /metrics)
  std::string_view listener_name() const;  // kListenerNames: "plain" or "tls"

  class Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

}  // namespace sms::gateway
