#pragma once
// The console's connections: an HTTP/1.1 connection (console_http.cpp), plain or over TLS, and
// the WebSocket it may become (console_websocket.cpp). A connection carries bytes, parses
// requests, keeps the door's ticket and ends the transport properly (close_notify over TLS); what
// a request means and whether it is allowed is its ConnectionHost's (ConsoleServer::Impl).
#include <chrono>
#include <cstddef>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>

#include "gateway/console/console_access.h"
#include "gateway/console/console_routes.h"
#include "gateway/console/console_server.h"
#include "gateway/net/door.h"
#include "protocol/expected.h"

namespace sms::gateway::console {

using HttpRequest = boost::beast::http::request<boost::beast::http::string_body>;

// Where a connection comes from.
struct Peer {
  bool loopback = false;
  std::string address;
  std::optional<Principal> certificate;  // HTTPS with a client certificate that has a role
  Door::Ticket ticket = 0;               // the connection's, at the console's door
  bool over_budget = false;              // it could not be trusted: answered 503, then closed
};

// Something open the server closes on stop().
class Connection {
 public:
  virtual ~Connection() = default;
  virtual void close() = 0;
};
// An open WebSocket, stepped by the server's timer.
class Socket : public Connection {
 public:
  virtual void tick(SteadyClock::time_point now, bool push) = 0;
};

// A WebSocket's route stream and the name of who opened it.
using OpenedSocket = std::pair<std::unique_ptr<Stream>, std::string>;

// What a connection needs of its server. Console thread only.
class ConnectionHost {
 public:
  virtual const ConsoleLimits& limits() const = 0;
  virtual Door& door() = 0;
  virtual void add(Connection* connection) = 0;
  virtual void remove(Connection* connection) = 0;
  virtual void add_socket(Socket* socket) = 0;
  virtual void remove_socket(Socket* socket) = 0;
  // The answer to one HTTP request; `done` may run later, once, on the console thread.
  virtual void handle_http(const HttpRequest& request, Peer& peer, std::function<void(HttpAnswer)> done) = 0;
  // A WebSocket upgrade: the stream to run, or the answer refusing it.
  virtual Expected<OpenedSocket, HttpAnswer> open_socket(const HttpRequest& request, Peer& peer) = 0;
  // The principal of a TLS connection's client certificate, once its handshake is done.
  virtual std::optional<Principal> certificate_principal(SSL* ssl) const = 0;

 protected:
  ~ConnectionHost() = default;
};

// Every response's Server header.
std::string_view console_server_name();

// Serves one accepted connection (over TLS when `tls` is set) until it closes; it first passes
// the host's door, which may refuse it at once.
void serve_connection(boost::asio::ip::tcp::socket socket, boost::asio::ssl::context* tls, ConnectionHost& host,
                      Peer peer);

}  // namespace sms::gateway::console
