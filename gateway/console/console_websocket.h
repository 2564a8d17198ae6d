#pragma once
// One WebSocket of the console: the route's stream stepped by the server's timer (samples every
// 10 ms, a batched push every 100 ms), a page's messages handed to it, a page that reads slower
// than the pushes come closed (it reconnects by itself).
#include <memory>
#include <string>

#include "gateway/console/console_connection.h"

namespace sms::gateway::console {

// Takes over `transport` (boost::beast::tcp_stream or ssl_stream of it) and the door's `ticket`
// from the HTTP connection that read the upgrade `request`, and accepts it.
template <typename Transport>
void start_websocket(Transport transport, ConnectionHost& host, OpenedSocket opened, Door::Ticket ticket,
                     HttpRequest request);

}  // namespace sms::gateway::console
