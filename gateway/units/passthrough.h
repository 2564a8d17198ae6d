#pragma once
// Transparent forwarding: Modbus TCP requests for a passthrough unit (`table:
// passthrough` on a modbus-rtu bus) — or, in `sms-gateway forward`, for any unit — go to a
// Modbus-RTU slave as they are, and its answer comes back as it is, exception PDUs included.
// So sms-gateway can replace a plain Modbus TCP -> RTU gateway.
//
// - Requests from every TCP connection are serialised on the bus by its engine's queue
//   (the bus engine with RtuTransactor: one exchange at a time, retries on CRC mismatch and timeouts).
// - The gateway's own exceptions (fault_from(), bus_faults.h): 0x0B the slave did not
//   answer through every retry, 0x0A its bus is down, 0x04 its answers stayed corrupt, 0x06 the
//   bus queue is full.
// - Slave 0 is an RTU broadcast: sent, no answer awaited. As mbusd (the reference gateway) does
//   by default, the TCP client gets no answer either: clients configured for broadcasts (e.g.
//   pymodbus with broadcast enabled) expect none, and an unexpected one would be taken as the
//   answer to their next request. With BroadcastReply::Answer (`--reply-on-broadcast`, mbusd's
//   -b) the client gets one once the frame has left: the normal answer of a write (FC05/06
//   echo, FC15/16 address and quantity), the echo of the request for other functions. Read
//   functions (01 02 03 04 17, and 11 report slave ID) to unit 0 are answered 0x0A either way,
//   without bus traffic: nobody answers a broadcast read.
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "config/config.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/bus_join.h"
#include "gateway/service/request_handler.h"

namespace sms::gateway {

// The answer a TCP client gets when `pdu` went out as a broadcast; nullopt for read
// functions, which are not broadcast at all (0x0A).
std::optional<Bytes> broadcast_answer(std::span<const std::uint8_t> pdu);

// Forwards `pdu` to `slave` (0 = broadcast) on `engine` and answers `reply` on the io thread
// (through `post`). `label` names the unit in logs ("unit 20 (bus rtu, slave 20)").
// Call on the io thread.
enum class BroadcastReply : std::uint8_t { None, Answer };
// `motion_epoch`: the safety rules' admission of a write to a passthrough unit (gateway/units/safety.h).
void forward_pdu(BusEngine& engine, std::uint8_t slave, std::span<const std::uint8_t> pdu, const PostFn& post,
                 const Reply& reply, const std::string& label, BroadcastReply broadcast_reply = BroadcastReply::None,
                 MotionEpoch motion_epoch = 0);

// `sms-gateway forward`: unit u (1-247) is RTU slave u, unit 0 the broadcast, any other unit
// (248-255) is answered 0x0A.
class ForwardHandler final : public RequestHandler {
 public:
  ForwardHandler(BusEngine& engine, PostFn post, BroadcastReply broadcast_reply = BroadcastReply::None);
  void handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) override;

 private:
  BusEngine& engine_;
  PostFn post_;
  BroadcastReply broadcast_reply_;
};

struct ForwardOptions {
  SerialSettings serial;                            // device, baud (any rate), parity, stop bits
  config::ModbusRtuOptions rtu;                     // RS-485 mode, RTS, byte timeout
  std::chrono::milliseconds response_timeout{100};  // a plain slave may take its time
  unsigned retries = 1;
  std::size_t queue_depth = 64;
  config::HostPort listen{"127.0.0.1", 5020};
  std::size_t max_connections = 32;
  std::chrono::seconds idle_timeout{60};
  BroadcastReply broadcast_reply = BroadcastReply::None;  // mbusd's default; -b / --reply-on-broadcast
};

// The whole `forward` program in one object (main and the tests use it the same way): an
// A modbus-rtu bus engine without servos, the ForwardHandler and the Modbus TCP server on an io thread.
class ForwardGateway {
 public:
  explicit ForwardGateway(ForwardOptions options);
  ~ForwardGateway();  // stop()
  ForwardGateway(const ForwardGateway&) = delete;
  ForwardGateway& operator=(const ForwardGateway&) = delete;

  // Listens, then opens the line (a missing device is retried by the engine). Throws
  // std::runtime_error when it cannot listen.
  void start();
  // Graceful: answers in flight first (at most `grace`), then the bus.
  void stop(std::chrono::milliseconds grace = std::chrono::seconds{5});
  std::uint16_t port() const;
  BusEngine& engine();

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
