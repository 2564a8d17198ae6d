// The console's HTTP/1.1 connections, plain or over TLS (console_connection.h).
#include <chrono>
#include <optional>
#include <string>
#include <type_traits>

#include <spdlog/spdlog.h>
#include <boost/asio/steady_timer.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>

#include "gateway/console/console_connection.h"
#include "gateway/console/console_websocket.h"

namespace sms::gateway::console {
namespace {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
namespace ssl = asio::ssl;
using tcp = asio::ip::tcp;
using TlsTransport = beast::ssl_stream<beast::tcp_stream>;

constexpr std::string_view kServerName = "sms-gateway/" SMS_GATEWAY_VERSION " console";
// Pages load scripts and styles from this server only; nothing inline, no framing by other sites.
constexpr std::string_view kContentSecurityPolicy =
    "default-src 'self'; img-src 'self' data:; connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; "
    "form-action 'self'";
// How long a TLS client has to answer the console's close_notify before the socket closes anyway.
constexpr std::chrono::seconds kCloseNotifyWait{1};

beast::string_view view(std::string_view text) { return {text.data(), text.size()}; }

// A read error's answer; nullopt: just close (timeouts, the client leaving, a stop).
std::optional<HttpAnswer> answer_for_read_error(const beast::error_code& error) {
  if (error == http::error::end_of_stream || error == http::error::partial_message) return std::nullopt;
  if (error == http::error::header_limit) return HttpAnswer::error(431, "request headers too large");
  if (error == http::error::body_limit) return HttpAnswer::error(413, "request body too large");
  if (error.category() == http::make_error_code(http::error::bad_method).category()) {
    return HttpAnswer::error(400, "not an HTTP/1.1 request: " + error.message());
  }
  return std::nullopt;
}

// Whether a read error leaves the transport fit for a close_notify: the client closed cleanly
// (its own close_notify, or a FIN between requests on plain HTTP), or sent what HTTP refuses.
bool transport_intact(const beast::error_code& error) {
  return error == http::error::end_of_stream || error == http::error::partial_message ||
         error.category() == http::make_error_code(http::error::bad_method).category();
}

template <typename Transport>
tcp::socket& socket_of(Transport& transport) {
  return beast::get_lowest_layer(transport).socket();
}

// One HTTP connection: requests answered one at a time; a WebSocket upgrade hands the
// connection over to a WebSocketSession. Over TLS every end the console chooses (a response
// with Connection: close, the client's close_notify answered, the request deadline, the door's
// eviction) is said with close_notify (RFC 8446 6.1), as the Modbus/TCP Security listener does; a
// transport that failed just closes.
template <typename Transport>
class HttpSession final : public Connection,
                          public DoorGuest,
                          public std::enable_shared_from_this<HttpSession<Transport>> {
  static constexpr bool kTls = std::is_same_v<Transport, TlsTransport>;

 public:
  HttpSession(Transport transport, ConnectionHost& host, Peer peer)
      : transport_(std::move(transport)),
        host_(host),
        peer_(std::move(peer)),
        deadline_(socket_of(transport_).get_executor()) {
    beast::error_code error;
    const auto endpoint = socket_of(transport_).remote_endpoint(error);
    peer_text_ = error ? peer_.address : peer_.address + ":" + std::to_string(endpoint.port());
    host_.add(this);
  }
  ~HttpSession() override { host_.remove(this); }

  // Through the door first (false: refused, closed); then, once the client's first bytes are
  // there, the TLS handshake or the first read: until then the connection is silent() without
  // doubt (nothing sits unseen in a TLS or HTTP parser's buffer).
  bool start() {
    const auto ticket = host_.door().admit(peer_.address, this->weak_from_this());
    if (!ticket) {
      close();
      return false;
    }
    peer_.ticket = *ticket;
    busy_ = true;
    socket_of(transport_)
        .async_wait(tcp::socket::wait_read, [self = this->shared_from_this()](const beast::error_code& error) {
          self->busy_ = false;
          if (self->closed_) return self->end_transport();
          self->spoke_ = true;
          if (error) {
            self->transport_failed_ = true;
            return self->close();
          }
          self->begin();
        });
    return true;
  }

  // DoorGuest
  void close_by_door() override { close(); }
  bool silent() const override {
    if (spoke_ || closed_) return false;
    // Bytes the kernel holds that the session has not read yet: the client did speak.
    beast::error_code error;
    const std::size_t unread = socket_of(const_cast<Transport&>(transport_)).available(error);
    return error || unread == 0;
  }
  const std::string& peer() const override { return peer_text_; }

  // Connection: the console's own end of the connection.
  void close() override {
    if (closed_) return;
    closed_ = true;
    deadline_.cancel();
    if (!handed_over_) host_.door().leave(peer_.ticket);
    end_transport();
  }

 private:
  void begin() {
    if constexpr (kTls) {
      busy_ = true;
      beast::get_lowest_layer(transport_).expires_after(host_.limits().request_timeout);
      transport_.async_handshake(
          ssl::stream_base::server, [self = this->shared_from_this()](const beast::error_code& error) {
            self->busy_ = false;
            if (error) {
              if (!self->closed_) {
                spdlog::debug("console: TLS handshake with {} failed: {}", self->peer_.address, error.message());
              }
              self->transport_failed_ = true;
              return self->closed_ ? self->end_transport() : self->close();
            }
            self->tls_up_ = true;
            if (self->closed_) return self->end_transport();
            self->peer_.certificate = self->host_.certificate_principal(self->transport_.native_handle());
            self->read();
          });
    } else {
      read();
    }
  }

  // The next request, within the request timeout (the console's own timer, so that a TLS
  // client still gets close_notify when it runs out).
  void read() {
    parser_.emplace();
    parser_->header_limit(static_cast<std::uint32_t>(host_.limits().max_header_bytes));
    parser_->body_limit(host_.limits().max_body_bytes);
    beast::get_lowest_layer(transport_).expires_never();
    deadline_.expires_after(host_.limits().request_timeout);
    deadline_.async_wait([weak = this->weak_from_this()](const beast::error_code& error) {
      if (error) return;
      if (auto self = weak.lock()) self->close();
    });
    busy_ = true;
    http::async_read(
        transport_, buffer_, *parser_,
        [self = this->shared_from_this()](const beast::error_code& error, std::size_t) { self->on_read(error); });
  }

  void on_read(const beast::error_code& error) {
    busy_ = false;
    deadline_.cancel();
    if (closed_) return end_transport();
    if (error) {
      if (!transport_intact(error)) transport_failed_ = true;
      if (auto answer = answer_for_read_error(error)) return write(std::move(*answer), false, 11);
      return close();
    }
    host_.door().heard(peer_.ticket);
    auto request = parser_->release();
    if (websocket::is_upgrade(request)) {
      auto opened = host_.open_socket(request, peer_);
      if (!opened) return write(opened.error(), false, request.version());
      handed_over_ = true;
      closed_ = true;  // this object's part is over: the socket and the ticket are the WebSocket's
      start_websocket(std::move(transport_), host_, std::move(*opened), peer_.ticket, std::move(request));
      return;
    }
    const bool keep_alive = request.keep_alive();
    const unsigned version = request.version();
    const bool head = request.method() == http::verb::head;
    if (head) request.method(http::verb::get);
    host_.handle_http(request, peer_, [self = this->shared_from_this(), keep_alive, version, head](HttpAnswer answer) {
      if (self->closed_) return;  // evicted or stopped while the answer was made
      if (head) answer.body.clear();
      self->write(std::move(answer), keep_alive && !self->peer_.over_budget, version);
    });
  }

  void write(HttpAnswer answer, bool keep_alive, unsigned version) {
    response_.emplace(static_cast<http::status>(answer.status), version);
    response_->set(http::field::server, view(kServerName));
    response_->set(http::field::content_type, answer.content_type);
    response_->set("Content-Security-Policy", view(kContentSecurityPolicy));
    response_->set("X-Content-Type-Options", "nosniff");
    response_->set("Referrer-Policy", "no-referrer");
    bool cache_set = false;
    for (const auto& [name, value] : answer.headers) {
      response_->insert(name, value);
      cache_set = cache_set || name == "Cache-Control";
    }
    if (!cache_set) response_->set(http::field::cache_control, "no-store");
    response_->keep_alive(keep_alive);
    response_->body() = std::move(answer.body);
    response_->prepare_payload();
    beast::get_lowest_layer(transport_).expires_after(host_.limits().request_timeout);
    busy_ = true;
    http::async_write(transport_, *response_,
                      [self = this->shared_from_this(), keep_alive](const beast::error_code& error, std::size_t) {
                        self->busy_ = false;
                        self->response_.reset();
                        if (self->closed_) return self->end_transport();
                        if (error) self->transport_failed_ = true;
                        if (error || !keep_alive) return self->close();
                        self->read();
                      });
  }

  // After close(): over an intact TLS session the close_notify (once no read or write is in
  // progress: those are cancelled and come back here), bounded by kCloseNotifyWait; then the
  // socket.
  void end_transport() {
    if (transport_ended_ || handed_over_) return;
    if constexpr (kTls) {
      if (tls_up_ && !transport_failed_) {
        if (busy_) {
          beast::error_code ignored;
          socket_of(transport_).cancel(ignored);
          return;
        }
        transport_ended_ = true;
        beast::get_lowest_layer(transport_).expires_after(kCloseNotifyWait);
        transport_.async_shutdown(
            [self = this->shared_from_this()](const beast::error_code&) { self->close_socket(); });
        return;
      }
    }
    transport_ended_ = true;
    close_socket();
  }

  void close_socket() {
    beast::error_code ignored;
    socket_of(transport_).shutdown(tcp::socket::shutdown_both, ignored);
    socket_of(transport_).close(ignored);
  }

  Transport transport_;
  ConnectionHost& host_;
  Peer peer_;
  std::string peer_text_;
  asio::steady_timer deadline_;    // for the request being read
  bool spoke_ = false;             // the client's first bytes came (or its connection failed)
  bool closed_ = false;            // the console is done with the connection (close() or handed over)
  bool handed_over_ = false;       // to a WebSocketSession, with the door's ticket
  bool busy_ = false;              // a wait, handshake, read or write is in progress
  bool tls_up_ = false;            // the handshake succeeded: an end is said with close_notify
  bool transport_failed_ = false;  // a read, write or handshake failed: no close_notify
  bool transport_ended_ = false;
  beast::flat_buffer buffer_;
  std::optional<http::request_parser<http::string_body>> parser_;
  std::optional<http::response<http::string_body>> response_;
};

}  // namespace

std::string_view console_server_name() { return kServerName; }

void serve_connection(tcp::socket socket, ssl::context* tls, ConnectionHost& host, Peer peer) {
  if (tls != nullptr) {
    std::make_shared<HttpSession<TlsTransport>>(TlsTransport(beast::tcp_stream(std::move(socket)), *tls), host,
                                                std::move(peer))
        ->start();
  } else {
    std::make_shared<HttpSession<beast::tcp_stream>>(beast::tcp_stream(std::move(socket)), host, std::move(peer))
        ->start();
  }
}

}  // namespace sms::gateway::console
