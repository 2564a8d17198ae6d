#pragma once
// Opening a TCP listening socket with an error that says what to do, and stopping a server that
// runs its own io thread: shared by the Modbus TCP server, the metrics endpoint and the console
// (internal to gateway/; Asio in the header is fine here).
//
//   open_listener(acceptor, "127.0.0.1", 502, {"listen for Modbus TCP", "--listen HOST:PORT or modbus_tcp.listen",
//   5020});
#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <thread>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>

namespace sms::gateway {

// Who listens, for the error text.
struct ListenerRole {
  std::string_view action;          // "listen for Modbus TCP", "serve metrics"
  std::string_view setting;         // where the address is set: "--listen HOST:PORT or modbus_tcp.listen"
  std::uint16_t unprivileged_port;  // a port to suggest when one below 1024 is refused
};

// Resolves `host` (an IP address, or a name), then opens, binds (SO_REUSEADDR) and listens.
// Throws std::runtime_error "cannot <action> on HOST:PORT: <reason>; <what to do>".
void open_listener(boost::asio::ip::tcp::acceptor& acceptor, const std::string& host, std::uint16_t port,
                   const ListenerRole& role);

// Stops a server whose `thread` runs `io`: `close_all` runs on that thread (its sessions are the
// thread's own) and is waited for, then the loop ends and the thread is joined. Nothing when the
// thread is not running. Not from `thread` itself.
void close_and_join(boost::asio::io_context& io, std::thread& thread, const std::function<void()>& close_all);

}  // namespace sms::gateway
