#pragma once
// One Modbus TCP connection (internal to the TCP server; tests drive it through TcpServer).
// Plain connections are MbapSession<tcp::socket>; Modbus/TCP Security connections are
// MbapSession<ssl::stream<tcp::socket>>, which first completes the TLS handshake (the door's
// deadline: modbus_tcp.tls.handshake_timeout_ms) and asks the server's TlsService for the connection's handler (a
// RoleGate in front of the router), then runs exactly as a plain one. The session owns its socket, read buffer and MBAP
// decoder and keeps itself alive with shared_from_this() in every pending handler, as the classic Asio server examples
// do.
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
#include <type_traits>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/ssl/stream.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/modbus_tcp/tcp_server.h"
#include "gateway/net/door.h"
#include "protocol/modbus_tcp.h"

namespace sms::gateway {

class TlsService;

// What the server holds of a session, whatever its stream. The listener's door
// (gateway/net/door.h) sees it as a guest: it may close it to make room or for its deadline.
class Session : public DoorGuest {
 public:
  virtual ~Session() = default;
  virtual void start() = 0;
  // Finish the request being answered, write its answer, then close.
  virtual void drain() = 0;
  // Close now; an answer still to come is dropped.
  virtual void close() = 0;
  const std::string& peer() const override = 0;
  // Nothing came from the client yet (a connection opened and left silent); such connections
  // are the first to make room for new ones.
  bool silent() const override = 0;
  void close_by_door() override { close(); }
  // The door's ticket of this connection (set by the server on accept).
  Door::Ticket ticket = 0;
};

// What a session needs from its server.
class SessionHost {
 public:
  virtual RequestHandler& handler() = 0;
  virtual const TcpServerOptions& options() const = 0;
  virtual TlsService* tls() = 0;  // nullptr on a plain listener
  virtual void on_session_closed(const std::shared_ptr<Session>& session) = 0;
  // The TLS handshake succeeded, or (plain) the first complete request came: false when the
  // connection may not be served (the limit of served connections is reached; the host has
  // counted and logged it) and must close.
  virtual bool trust(const std::shared_ptr<Session>& session) = 0;
  virtual void count_request(std::span<const std::uint8_t> pdu) = 0;
  virtual void count_response(std::span<const std::uint8_t> pdu) = 0;
  virtual void count_bad_header() = 0;
  virtual void count_idle_close() = 0;

 protected:
  ~SessionHost() = default;
};

template <typename Stream>
class MbapSession final : public Session,
                          public Reply::Target,
                          public std::enable_shared_from_this<MbapSession<Stream>> {
 public:
  // `keep_alive`: what the stream needs to outlive it (the TLS context it was made from).
  MbapSession(Stream stream, std::shared_ptr<SessionHost> host, std::shared_ptr<void> keep_alive = nullptr);

  void start() override;
  void drain() override;
  void close() override;
  const std::string& peer() const override { return peer_; }
  bool silent() const override;

  void deliver(std::uint64_t request_serial, Bytes response_pdu) override;

 private:
  static constexpr bool kTls = !std::is_same_v<Stream, boost::asio::ip::tcp::socket>;

  typename Stream::lowest_layer_type& socket() { return stream_.lowest_layer(); }
  void start_handshake();
  void on_handshake(const boost::system::error_code& error);
  void begin_serving();
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
  void end_transport();  // after close(): close_notify (TLS), then the socket
  void close_socket();
  void arm_idle_timer(std::chrono::steady_clock::time_point deadline);
  void on_idle_timer(const boost::system::error_code& error);
  bool busy() const { return in_flight_.has_value() || !pending_.empty() || writing_; }
  bool answers_backed_up() const;

  std::shared_ptr<void> keep_alive_;  // before stream_: destroyed after it
  Stream stream_;
  boost::asio::steady_timer idle_timer_;
  std::shared_ptr<SessionHost> host_;
  std::string peer_;
  RequestHandler* handler_ = nullptr;  // the host's, or own_handler_ (TLS)
  std::unique_ptr<RequestHandler> own_handler_;
  bool handshaking_ = false;
  bool client_spoke_ = false;      // the client's first bytes came (TLS: or its connection failed)
  bool trusted_ = false;           // the host counts it served (TLS: handshake done; plain: a request came)
  bool admitted_ = false;          // TLS: counted open by the TlsService
  bool tls_up_ = false;            // TLS: the handshake succeeded
  bool transport_failed_ = false;  // a read or write failed: no close_notify
  bool transport_ended_ = false;
  static constexpr std::chrono::seconds kCloseNotifyWait{1};

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

using PlainSession = MbapSession<boost::asio::ip::tcp::socket>;
using TlsSession = MbapSession<boost::asio::ssl::stream<boost::asio::ip::tcp::socket>>;

}  // namespace sms::gateway
