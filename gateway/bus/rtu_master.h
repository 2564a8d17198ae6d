#pragma once
// The `modbus-rtu` line (docs/PROTOCOL.md §1.3): libmodbus as the RTU master, one request/reply exchange at
// a time, blocking, on the caller's thread (a bus thread, or a tool's). RtuTransactor
// (rtu_transactor.h) turns bus operations into these exchanges.
//
// Line rates: libmodbus 3.1.6 sets the rate with cfsetispeed/cfsetospeed and knows only the
// Bxxx constants (110 ... 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
// 1000000, 1152000, 1500000, 2500000 ... 4000000); any other rate it silently replaces with
// 9600. Of the Modbus baud table that is 256000, 128000, 56000 and 14400 (and 76800, 250000,
// 128000 ... of the packet tables). RtuMaster therefore sets every rate again through
// termios2/BOTHER (gateway/bus/serial_port_termios2.h) on modbus_get_socket()'s descriptor right
// after modbus_connect(): one code path for every rate.
//
// Timing (Modbus over serial line v1.02 §2.5.1): a frame is followed by 3.5 characters of
// silence (1.75 ms fixed above 19200 bit/s) before the next request; the reply timeout counts
// from when the request has left the wire; a broadcast is followed by a turnaround delay (the
// bus's response timeout) during which the slaves act on it.
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "config/config.h"
#include "gateway/bus/poll_cache.h"
#include "gateway/bus/serial_port.h"
#include "gateway/bus/wire_monitor.h"
#include "protocol/expected.h"

namespace sms::gateway {

struct RtuLineSettings {
  SerialSettings serial;
  config::ModbusRtuOptions options;  // RS-485 mode, RTS direction control and delay, byte timeout
};

// True when libmodbus 3.1.6 would set `baud` itself (a Bxxx constant exists for it).
bool libmodbus_sets_rate(std::uint32_t baud);

// The silence before the next frame: `gap` spec: 3.5 character times, 1.75 ms above 19200 bit/s
// (Modbus over serial line v1.02 §2.5.1.1); 3.5chars: 3.5 character times at every rate; or a
// fixed time. Counted from the last byte on the wire.
std::chrono::nanoseconds rtu_frame_gap(const SerialSettings& serial, const config::FrameGap& gap = {});

enum class RtuOutcome : std::uint8_t {
  Reply,       // a frame from the addressed slave with a valid CRC (possibly an exception PDU)
  Sent,        // no reply awaited (broadcast): the frame has left and the turnaround passed
  Timeout,     // no complete frame in time
  Corrupt,     // a frame with a wrong CRC, or one cut short
  WrongSlave,  // a valid frame from another slave (a late reply, a duplicate address)
  PortError,   // the device failed (unplugged, EIO): close and reopen
};
std::string_view to_string(RtuOutcome outcome);

struct RtuExchange {
  RtuOutcome outcome;
  protocol::Bytes pdu;                      // Reply: function code first, no slave, no CRC
  std::string detail;                       // what went wrong, for logs
  std::optional<std::uint8_t> other_slave;  // WrongSlave: who answered, when the frame says so
  protocol::Bytes dropped;  // what the input held before the request, read and dropped: late answers, noise

  // A constructor rather than an aggregate, so `{outcome, pdu, detail}` leaves other_slave empty.
  RtuExchange(RtuOutcome result = RtuOutcome::Timeout, protocol::Bytes reply_pdu = {}, std::string what = {},
              std::optional<std::uint8_t> answering_slave = std::nullopt)
      : outcome(result), pdu(std::move(reply_pdu)), detail(std::move(what)), other_slave(answering_slave) {}
};

// One RTU line: not thread-safe, used by one thread (the bus thread, or a tool's main thread).
class RtuMaster {
 public:
  explicit RtuMaster(RtuLineSettings settings);
  ~RtuMaster();
  RtuMaster(const RtuMaster&) = delete;
  RtuMaster& operator=(const RtuMaster&) = delete;

  // Opens the device exclusively at the configured rate (termios2 for every rate), RS-485 mode
  // and RTS control when configured. The error names the device, what failed and what to do.
  Expected<Ok> open();
  void close();
  bool is_open() const;
  const RtuLineSettings& settings() const { return settings_; }
  // Changes the rate: the line is reopened when it is open (libmodbus keeps the rate it opened with).
  Expected<Ok> set_baud(std::uint32_t baud);

  // Sends `pdu` to `slave` (1-247) and waits for the answer: its first byte within
  // `reply_timeout` after the request has left the wire, the rest with at most the byte
  // timeout between bytes. The input is read and dropped before sending (late replies, noise;
  // the bytes in the exchange's `dropped`).
  // Function codes whose answer length libmodbus knows (01-06, 0F, 10, 11, 16, 17 and every
  // exception) go through modbus_send_raw_request/modbus_receive_confirmation; any other
  // code's answer ends when the line stays silent for the byte timeout.
  RtuExchange transact(std::uint8_t slave, std::span<const std::uint8_t> pdu, std::chrono::nanoseconds reply_timeout);
  // Sends without awaiting an answer (slave 0 = broadcast): returns once the frame has left
  // the wire and `turnaround` has passed, so the slaves have acted before the next request.
  RtuExchange send_only(std::uint8_t slave, std::span<const std::uint8_t> pdu, std::chrono::nanoseconds turnaround);

  // For the upstream RTU slave port (gateway/rtu_slave), which opens its line through open() (the
  // same rates, RS-485 mode and RTS control) and frames requests itself: the descriptor to read
  // (-1 when closed), and an answer sent through libmodbus (CRC appended, RTS switched around
  // it) without flushing the input or waiting for a frame gap. An error means the device failed.
  int native_handle() const;
  Expected<Ok> send_frame(std::uint8_t slave, std::span<const std::uint8_t> pdu);
  // Awaits one more answer after transact() handed back a frame that was not the request's (an
  // answer the slave owed to an earlier request): its first byte within `timeout`.
  RtuExchange receive(std::uint8_t slave, std::uint8_t function, std::chrono::nanoseconds timeout);

  // The time `bytes` characters take on the line.
  std::chrono::nanoseconds wire_time(std::size_t bytes) const { return gateway::wire_time(settings_.serial, bytes); }

  // The bus monitor's tap (wire_monitor.h): the frames transact() and send_only() send, the
  // answers libmodbus hands back whole, and whatever else is read from the line are also recorded
  // there (an answer libmodbus rejects — bad CRC — is not handed back, so not recorded). nullptr:
  // nothing is recorded. Set before the bus thread starts.
  void set_monitor(WireMonitor* monitor) { monitor_ = monitor; }

 private:
  struct Line;
  RtuExchange receive_answer(std::uint8_t slave, std::uint8_t function, std::chrono::nanoseconds response_timeout);
  RtuExchange receive_until_silence(std::uint8_t slave, std::chrono::nanoseconds first_byte_timeout);
  void wait_for_frame_gap();
  // Reads what the input holds (modbus_flush's tcflush would not say which bytes): those bytes.
  protocol::Bytes drop_input();
  // What transact() and send_only() both do first: the line open, the PDU's size, the frame gap,
  // the input dropped, the request framed and written; with `answer_within`, the response
  // timeout set first (from when the request has left the wire). `failure`: a PortError, not sent.
  struct Sending {
    protocol::Bytes request;  // slave address and PDU, as written (the CRC is libmodbus's)
    protocol::Bytes dropped;
    std::chrono::nanoseconds response_timeout{};
    std::optional<RtuExchange> failure;
  };
  Sending send_request(std::uint8_t slave, std::span<const std::uint8_t> pdu, std::string_view caller,
                       std::optional<std::chrono::nanoseconds> answer_within);

  void tap(WireDirection direction, std::span<const std::uint8_t> bytes) const;
  void tap_request(std::span<const std::uint8_t> slave_and_pdu) const;

  RtuLineSettings settings_;
  std::unique_ptr<Line> line_;
  WireMonitor* monitor_ = nullptr;
};

}  // namespace sms::gateway
