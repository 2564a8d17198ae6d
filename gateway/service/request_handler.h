#pragma once
// How a Modbus request reaches whatever answers it, and how its answer goes back: the seam
// between the ways in (the TCP listeners, an upstream RTU port, the Sparkplug node) and the unit
// router. Kept apart from the TCP server so units/, mqtt/ and rtu_slave/ need none of it.
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include "protocol/packet.h"

namespace sms::gateway {

using protocol::Bytes;

// Where the answer to one request goes. Copyable so it can ride in bus completions; only the
// first send() for a request counts. Call send() on the server's io_context thread only.
// When the client has gone meanwhile the answer is dropped (the work itself still happened).
class Reply {
 public:
  class Target {
   public:
    virtual void deliver(std::uint64_t request_serial, Bytes response_pdu) = 0;

   protected:
    ~Target() = default;
  };

  // `origin`: who sent the request, for the log lines of what it changes ("an RTU panel on
  // /dev/ttyUSB1", "the Sparkplug host"); empty: a Modbus TCP client.
  Reply(std::shared_ptr<Target> target, std::uint64_t request_serial,
        std::shared_ptr<const std::string> origin = nullptr)
      : target_(std::move(target)), request_serial_(request_serial), origin_(std::move(origin)) {}
  std::string_view origin() const {
    return origin_ ? std::string_view(*origin_) : std::string_view("a Modbus TCP client");
  }
  const std::shared_ptr<const std::string>& origin_text() const { return origin_; }
  void send(Bytes response_pdu) const { target_->deliver(request_serial_, std::move(response_pdu)); }
  // The request is done and gets no answer (a broadcast, as Modbus TCP gateways answer them by
  // default): the connection goes on with its next request.
  void finish_without_answer() const { target_->deliver(request_serial_, {}); }

 private:
  std::shared_ptr<Target> target_;
  std::uint64_t request_serial_;
  std::shared_ptr<const std::string> origin_;
};

// Answers requests. Called on the io_context thread, one request at a time per connection
// (the next request of a connection is handed over only after reply.send()). reply.send()
// may be called before handle() returns (answers from memory) or later (bus work).
class RequestHandler {
 public:
  virtual ~RequestHandler() = default;
  virtual void handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) = 0;
};

}  // namespace sms::gateway
