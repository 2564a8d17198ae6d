#pragma once
// One Modbus TCP connection (internal to the TCP server; tests drive it through TcpServer).
// The session owns its socket, read buffer and MBAP decoder and keeps itself alive with
// shared_from_this() in every pending handler, as the classic Asio server examples do.
//
//   read -> MbapDecoder -> pending requests -> handler (one at a time) -> outbox -> write
//
// Answers are appended to the outbox in request order and written as they come; reading goes
// on while a request is being answered (pipelining) until max_pipelined requests wait, and no
// request is started while max_unsent_bytes of answers wait for the client to read them.
#include <array>
#include <chrono>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/tcp_server.h"
#include "protocol/modbus_tcp.h"

namespace sms::gateway {

class MbapSession;

// What a session needs from its server.
class SessionHost {
 public:
  virtual RequestHandler& handler() = 0;
  virtual const TcpServerOptions& options() const = 0;
  virtual void on_session_closed(const std::shared_ptr<MbapSession>& session) = 0;
  virtual void count_request(std::span<const std::uint8_t> pdu) = 0;
  virtual void count_response(std::span<const std::uint8_t> pdu) = 0;
  virtual void count_bad_header() = 0;
  virtual void count_idle_close() = 0;

 protected:
  ~SessionHost() = default;
};

class MbapSession final : public std::enable_shared_from_this<MbapSession>, public Reply::Target {
 public:
  MbapSession(boost::asio::ip::tcp::socket socket, std::shared_ptr<SessionHost> host);

  void start();
  // Finish the request being answered, write its answer, then close.
  void drain();
  // Close now; an answer still to come is dropped.
  void close();

  const std::string& peer() const { return peer_; }

  void deliver(std::uint64_t request_serial, Bytes response_pdu) override;

 private:
  struct InFlight {
    std::uint64_t serial = 0;
    std::uint16_t transaction_id = 0;
    std::uint8_t unit_id = 0;
  };

  void read_some();
  void on_read(const boost::system::error_code& error, std::size_t size);
  void process_pending();
  void flush();
  void on_written(const boost::system::error_code& error);
  void close_when_done();
  void arm_idle_timer(std::chrono::steady_clock::time_point deadline);
  void on_idle_timer(const boost::system::error_code& error);
  bool busy() const { return in_flight_.has_value() || !pending_.empty() || writing_; }
  bool answers_backed_up() const;

  boost::asio::ip::tcp::socket socket_;
  boost::asio::steady_timer idle_timer_;
  std::shared_ptr<SessionHost> host_;
  std::string peer_;

  std::array<std::uint8_t, 4096> read_buffer_{};
  protocol::tcp::MbapDecoder decoder_;
  std::deque<protocol::tcp::Frame> pending_;
  std::optional<InFlight> in_flight_;
  std::uint64_t next_serial_ = 1;

  Bytes outbox_;        // answers waiting for the current write to finish
  Bytes write_buffer_;  // the bytes of the write in progress
  bool writing_ = false;
  bool reading_ = false;
  bool processing_ = false;  // inside process_pending(): a synchronous answer must not recurse
  bool draining_ = false;    // no more requests; close once the in-flight answer is written
  bool closed_ = false;
  std::chrono::steady_clock::time_point last_activity_;
  std::chrono::steady_clock::time_point write_started_;  // of the write in progress
};

}  // namespace sms::gateway
