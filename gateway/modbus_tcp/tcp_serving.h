#pragma once
// The Modbus TCP side of a running gateway: its io_context, the thread that runs it and the
// TcpServer on it. Gateway and ForwardGateway (passthrough.h) both run their TCP side this way;
// what differs is the handler and the buses behind it. Asio stays out of this header.
//
//   TcpServing serving;
//   serving.listen(options, handler);   // throws std::runtime_error: address in use, ...
//   ... start the buses ...
//   serving.run();                      // connections are served from here on
//   ...
//   serving.drain(5s);                  // answers in flight first
//   ... stop the buses ...
//   serving.stop();
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "gateway/modbus_tcp/tcp_server.h"

namespace boost::asio {
class io_context;
}

namespace sms::gateway {

class TcpServing {
 public:
  TcpServing();
  ~TcpServing();  // closes every connection and ends the thread
  TcpServing(const TcpServing&) = delete;
  TcpServing& operator=(const TcpServing&) = delete;

  // Runs `work` on the io thread (bus completions come back this way).
  void post(std::function<void()> work);
  // The io_context the thread runs: for parts that live on the io thread (the Sparkplug node).
  boost::asio::io_context& io();
  // Binds and listens; connections wait in the backlog until run(). Throws std::runtime_error
  // naming the address and what to do. Called once per listener (plain Modbus TCP, Modbus/TCP
  // Security); returns the listener's index for port(index).
  std::size_t listen(TcpServerOptions options, RequestHandler& handler);
  // Starts the io thread.
  void run();
  // Graceful part of a stop: no new connections; each connection's request in flight is
  // answered, then the connection closes. After `grace` the rest are closed regardless.
  void drain(std::chrono::milliseconds grace);
  // Ends the io thread. Call after the buses have stopped (their completions post here).
  // Idempotent.
  void stop();

  std::uint16_t port(std::size_t index = 0) const;  // 0 when there is no such listener
  TcpServerStats stats() const;                     // summed over the listeners
  // Each listener's door, named as /metrics labels it ("plain", "tls").
  std::vector<std::pair<std::string, DoorStats>> doors() const;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
