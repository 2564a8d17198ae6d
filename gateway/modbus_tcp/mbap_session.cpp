#include "gateway/modbus_tcp/mbap_session.h"

#include <spdlog/spdlog.h>
#include <boost/asio/write.hpp>

#include "gateway/modbus_tcp/tls.h"

namespace sms::gateway {
namespace {

template <typename Socket>
std::string endpoint_text(const Socket& socket) {
  boost::system::error_code error;
  const auto endpoint = socket.remote_endpoint(error);
  if (error) return "(unknown peer)";
  return endpoint.address().to_string() + ":" + std::to_string(endpoint.port());
}

}  // namespace

template <typename Stream>
MbapSession<Stream>::MbapSession(Stream stream, std::shared_ptr<SessionHost> host, std::shared_ptr<void> keep_alive)
    : keep_alive_(std::move(keep_alive)),
      stream_(std::move(stream)),
      idle_timer_(stream_.get_executor()),
      host_(std::move(host)),
      peer_(endpoint_text(stream_.lowest_layer())),
      last_activity_(std::chrono::steady_clock::now()) {}

template <typename Stream>
void MbapSession<Stream>::start() {
  boost::system::error_code ignored;
  // Modbus answers are small and latency matters more than packet count.
  socket().set_option(boost::asio::ip::tcp::no_delay(true), ignored);
  if constexpr (kTls) {
    handshaking_ = true;
    // The handshake starts once the client's first bytes are there: until then the connection
    // is silent() without doubt (no bytes sitting unseen in a read buffer of the TLS stream).
    socket().async_wait(
        boost::asio::socket_base::wait_read,
        [self = this->shared_from_this()](const boost::system::error_code&) { self->start_handshake(); });
  } else {
    handler_ = &host_->handler();
    begin_serving();
  }
}

template <typename Stream>
void MbapSession<Stream>::start_handshake() {
  if constexpr (kTls) {
    if (closed_) return;
    client_spoke_ = true;  // or its connection failed: the handshake says which
    stream_.async_handshake(
        boost::asio::ssl::stream_base::server,
        [self = this->shared_from_this()](const boost::system::error_code& error) { self->on_handshake(error); });
  }
}

template <typename Stream>
void MbapSession<Stream>::on_handshake(const boost::system::error_code& error) {
  handshaking_ = false;
  if (closed_) return;  // timed out, or the server stopped
  if constexpr (kTls) {
    if (error) {
      host_->tls()->handshake_failed(error, stream_.native_handle(), peer_);
      close();
      return;
    }
    tls_up_ = true;  // from here on a close is said with close_notify
    if (!host_->trust(this->shared_from_this())) {
      close();
      return;
    }
    trusted_ = true;
    own_handler_ = host_->tls()->admit(stream_.native_handle(), peer_);
    if (!own_handler_) {
      close();
      return;
    }
    admitted_ = true;
    handler_ = own_handler_.get();
    last_activity_ = std::chrono::steady_clock::now();
    begin_serving();
  }
}

template <typename Stream>
bool MbapSession<Stream>::silent() const {
  if (closed_ || client_spoke_) return false;
  boost::system::error_code error;
  // Bytes the kernel holds that the gateway has not read yet: the client did speak. A socket
  // in error is as good as silent.
  const std::size_t unread = const_cast<MbapSession*>(this)->socket().available(error);
  return error || unread == 0;
}

template <typename Stream>
void MbapSession<Stream>::begin_serving() {
  const auto idle = host_->options().idle_timeout;
  if (idle.count() > 0) {
    arm_idle_timer(last_activity_ + idle);
  } else {
    idle_timer_.cancel();
  }
  read_some();
}

template <typename Stream>
void MbapSession<Stream>::read_some() {
  if (closed_ || draining_ || reading_ || handshaking_ || decoder_.failed()) return;
  if (pending_.size() >= host_->options().max_pipelined) return;  // resumed by process_pending
  reading_ = true;
  stream_.async_read_some(boost::asio::buffer(read_buffer_),
                          [self = this->shared_from_this()](const boost::system::error_code& error, std::size_t size) {
                            self->on_read(error, size);
                          });
}

template <typename Stream>
void MbapSession<Stream>::on_read(const boost::system::error_code& error, std::size_t size) {
  reading_ = false;
  if (closed_) {
    end_transport();
    return;
  }
  if (error) {
    // After the peer's close_notify (eof) the close_notify is answered; a transport that failed
    // or was cut without one (stream_truncated) takes no more bytes.
    if (error != boost::asio::error::eof) transport_failed_ = true;
    if (error != boost::asio::error::eof && error != boost::asio::error::connection_reset &&
        error != boost::asio::error::operation_aborted && error != boost::asio::ssl::error::stream_truncated) {
      spdlog::warn("modbus tcp: connection {}: read failed: {}", peer_, error.message());
    }
    // The client is gone: nothing more can be answered. Bus work already handed over still
    // completes (a write it started is not taken back); its answer is dropped in deliver().
    close();
    return;
  }
  last_activity_ = std::chrono::steady_clock::now();
  client_spoke_ = true;
  if (draining_) return;  // shutting down: requests arriving now are not started

  decoder_.feed(std::span<const std::uint8_t>(read_buffer_.data(), size));
  while (auto event = decoder_.next()) {
    if (auto* frame = std::get_if<protocol::tcp::Frame>(&*event)) {
      // Plain: the first complete request is what lets a connection be served.
      if (!trusted_) {
        if (!host_->trust(this->shared_from_this())) {
          close();
          return;
        }
        trusted_ = true;
      }
      pending_.push_back(std::move(*frame));
      continue;
    }
    const auto& bad = std::get<protocol::tcp::BadHeader>(*event);
    spdlog::warn("modbus tcp: connection {}: {}; closing it after answering the {} request(s) before it", peer_,
                 bad.reason, pending_.size() + (in_flight_ ? 1 : 0));
    host_->count_bad_header();
    draining_ = true;  // answer what came before the bad header, then close
    break;
  }
  process_pending();
  read_some();
  close_when_done();
}

template <typename Stream>
void MbapSession<Stream>::process_pending() {
  if (processing_) return;
  processing_ = true;
  while (!closed_ && !in_flight_ && !pending_.empty() && !answers_backed_up()) {
    protocol::tcp::Frame frame = std::move(pending_.front());
    pending_.pop_front();
    in_flight_ = InFlight{next_serial_++, frame.transaction_id, frame.unit_id};
    host_->count_request(frame.pdu);
    // May answer at once (deliver() runs inside) or later from a bus completion.
    handler_->handle(frame.unit_id, frame.pdu, Reply(this->shared_from_this(), in_flight_->serial));
  }
  processing_ = false;
  read_some();  // resumes reading if the pipeline limit had paused it
}

template <typename Stream>
void MbapSession<Stream>::deliver(std::uint64_t request_serial, Bytes response_pdu) {
  if (closed_) {
    spdlog::debug("modbus tcp: connection {} closed before its answer was ready; answer dropped", peer_);
    return;
  }
  if (!in_flight_ || in_flight_->serial != request_serial) return;  // answered already
  if (!response_pdu.empty()) {                                      // empty: Reply::finish_without_answer()
    host_->count_response(response_pdu);
    const Bytes adu = protocol::tcp::encode_mbap(in_flight_->transaction_id, in_flight_->unit_id, response_pdu);
    outbox_.insert(outbox_.end(), adu.begin(), adu.end());
  }
  in_flight_.reset();
  flush();
  process_pending();
  close_when_done();
}

template <typename Stream>
bool MbapSession<Stream>::answers_backed_up() const {
  return outbox_.size() + write_buffer_.size() >= host_->options().max_unsent_bytes;
}

template <typename Stream>
void MbapSession<Stream>::flush() {
  if (writing_ || outbox_.empty() || closed_) return;
  write_buffer_.swap(outbox_);
  outbox_.clear();
  writing_ = true;
  write_started_ = std::chrono::steady_clock::now();
  boost::asio::async_write(stream_, boost::asio::buffer(write_buffer_),
                           [self = this->shared_from_this()](const boost::system::error_code& error, std::size_t) {
                             self->on_written(error);
                           });
}

template <typename Stream>
void MbapSession<Stream>::on_written(const boost::system::error_code& error) {
  writing_ = false;
  write_buffer_.clear();
  if (closed_) {
    end_transport();
    return;
  }
  if (error) {
    transport_failed_ = true;
    if (error != boost::asio::error::broken_pipe && error != boost::asio::error::connection_reset) {
      spdlog::warn("modbus tcp: connection {}: write failed: {}", peer_, error.message());
    }
    close();
    return;
  }
  flush();
  process_pending();  // requests held back while answers were backed up
  close_when_done();
}

template <typename Stream>
void MbapSession<Stream>::drain() {
  if (closed_) return;
  draining_ = true;
  pending_.clear();  // never started, never answered: the client cannot take them as done
  close_when_done();
}

template <typename Stream>
void MbapSession<Stream>::close_when_done() {
  if (draining_ && !closed_ && !in_flight_ && pending_.empty() && !writing_ && outbox_.empty()) close();
}

template <typename Stream>
void MbapSession<Stream>::close() {
  if (closed_) return;
  closed_ = true;
  pending_.clear();
  idle_timer_.cancel();
  end_transport();
  if (admitted_) host_->tls()->connection_closed();
  host_->on_session_closed(this->shared_from_this());
}

template <typename Stream>
void MbapSession<Stream>::end_transport() {
  if (transport_ended_) return;
  if constexpr (kTls) {
    // A TLS peer is told the close with close_notify (RFC 8446 6.1), so it can tell the end from
    // a cut connection: once no read or write is in progress (those are cancelled and come back
    // here), the alert is sent and the peer's answered, bounded by kCloseNotifyWait.
    if (tls_up_ && !transport_failed_) {
      if (reading_ || writing_) {
        boost::system::error_code ignored;
        socket().cancel(ignored);
        return;
      }
      transport_ended_ = true;
      idle_timer_.expires_after(kCloseNotifyWait);
      idle_timer_.async_wait([self = this->shared_from_this()](const boost::system::error_code& error) {
        if (!error) self->close_socket();
      });
      stream_.async_shutdown([self = this->shared_from_this()](const boost::system::error_code&) {
        self->idle_timer_.cancel();
        self->close_socket();
      });
      return;
    }
  }
  transport_ended_ = true;
  close_socket();
}

template <typename Stream>
void MbapSession<Stream>::close_socket() {
  boost::system::error_code ignored;
  socket().shutdown(boost::asio::ip::tcp::socket::shutdown_both, ignored);
  socket().close(ignored);
}

template <typename Stream>
void MbapSession<Stream>::arm_idle_timer(std::chrono::steady_clock::time_point deadline) {
  idle_timer_.expires_at(deadline);
  idle_timer_.async_wait(
      [self = this->shared_from_this()](const boost::system::error_code& error) { self->on_idle_timer(error); });
}

template <typename Stream>
void MbapSession<Stream>::on_idle_timer(const boost::system::error_code& error) {
  if (error || closed_ || handshaking_) return;  // the handshake's deadline is the door's
  const auto idle = host_->options().idle_timeout;
  const auto now = std::chrono::steady_clock::now();
  if (writing_ && now - write_started_ >= idle) {
    spdlog::info("modbus tcp: connection {} has not taken its answers for {}; closing it", peer_, duration_text(idle));
    host_->count_idle_close();
    close();
    return;
  }
  // A request being answered is activity, however long the bus takes.
  if (busy()) {
    arm_idle_timer(now + idle);
    return;
  }
  if (now - last_activity_ >= idle) {
    spdlog::info("modbus tcp: connection {} idle for {}; closing it", peer_, duration_text(idle));
    host_->count_idle_close();
    close();
    return;
  }
  arm_idle_timer(last_activity_ + idle);
}

template class MbapSession<boost::asio::ip::tcp::socket>;
template class MbapSession<boost::asio::ssl::stream<boost::asio::ip::tcp::socket>>;

}  // namespace sms::gateway
