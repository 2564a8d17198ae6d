#include "gateway/modbus_tcp/tcp_server.h"

#include <algorithm>
#include <atomic>
#include <mutex>
#include <optional>
#include <set>
#include <stdexcept>

#include <spdlog/spdlog.h>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/modbus_tcp/access_policy.h"
#include "gateway/modbus_tcp/mbap_session.h"
#include "gateway/modbus_tcp/tls.h"
#include "gateway/modbus_tcp/traffic_counters.h"
#include "gateway/net/listener.h"

namespace sms::gateway {

namespace asio = boost::asio;
using asio::ip::tcp;

namespace {

// The door of a listener, from the server's options (plain) or the TLS settings.
DoorSettings door_settings(const TcpServerOptions& options) {
  if (options.tls == nullptr) {
    return {std::string(kListenerNames[0]),
            "modbus tcp",
            "complete Modbus request",
            DoorLimits{options.max_connections, options.max_waiting, options.max_waiting_per_address,
                       options.first_request_timeout},
            DoorLimitNames{"modbus_tcp.max_connections", "modbus_tcp.max_waiting", "modbus_tcp.max_waiting_per_address",
                           "modbus_tcp.first_request_timeout_ms"},
            nullptr};
  }
  const config::TlsConfig& tls = options.tls->settings();
  return {
      std::string(kListenerNames[1]),
      "modbus tcp security",
      "complete TLS handshake",
      DoorLimits{options.max_connections, tls.max_handshakes, tls.max_handshakes_per_address, tls.handshake_timeout},
      DoorLimitNames{"modbus_tcp.max_connections", "modbus_tcp.tls.max_handshakes",
                     "modbus_tcp.tls.max_handshakes_per_address", "modbus_tcp.tls.handshake_timeout_ms"},
      [service = options.tls](DoorClose why) { service->handshake_closed_by_door(why); }};
}

}  // namespace

class TcpServer::Impl final : public SessionHost, public std::enable_shared_from_this<TcpServer::Impl> {
 public:
  Impl(asio::io_context& io, TcpServerOptions options, RequestHandler& handler)
      : io_(io),
        options_(std::move(options)),
        handler_(handler),
        access_(options_.allow),
        door_(io, door_settings(options_)),
        acceptor_(io),
        retry_timer_(io) {}

  void start() {
    const std::string idle =
        options_.idle_timeout.count() > 0 ? duration_text(options_.idle_timeout) : std::string("off");
    if (options_.tls != nullptr) {
      open_listener(acceptor_, options_.host, options_.port,
                    {"listen for Modbus/TCP Security", "modbus_tcp.tls.listen in the configuration", 8020});
      port_ = acceptor_.local_endpoint().port();
      spdlog::info(
          "modbus tcp security: listening on {}:{} (TLS 1.2/1.3, client certificates of CA {} required; {}; idle "
          "timeout {}; clients allowed: {})",
          options_.host, port_, options_.tls->settings().ca, door_.describe(), idle, access_.describe());
    } else {
      open_listener(acceptor_, options_.host, options_.port,
                    {"listen for Modbus TCP", "--listen HOST:PORT or modbus_tcp.listen in the configuration", 5020});
      port_ = acceptor_.local_endpoint().port();
      spdlog::info("modbus tcp: listening on {}:{} ({}; idle timeout {}; clients allowed: {})", options_.host, port_,
                   door_.describe(), idle, access_.describe());
    }
    accept();
  }

  std::uint16_t port() const { return port_; }

  void shutdown(std::function<void()> done) {
    stop_accepting();
    on_all_closed_ = std::move(done);
    const auto sessions = sessions_;  // drain() may close and erase synchronously
    for (const auto& session : sessions) session->drain();
    notify_if_all_closed();
  }

  void close_all() {
    stop_accepting();
    const auto sessions = sessions_;
    for (const auto& session : sessions) session->close();
  }

  TcpServerStats stats() const {
    std::lock_guard lock(stats_mutex_);
    return stats_;
  }
  DoorStats door_stats() const { return door_.stats(); }

  // SessionHost
  RequestHandler& handler() override { return handler_; }
  const TcpServerOptions& options() const override { return options_; }
  TlsService* tls() override { return options_.tls; }
  void on_session_closed(const std::shared_ptr<Session>& session) override {
    door_.leave(session->ticket);
    if (sessions_.erase(session) == 0) return;
    spdlog::debug("{}: {} disconnected ({} open)", log_prefix(), session->peer(), sessions_.size());
    {
      std::lock_guard lock(stats_mutex_);
      stats_.open_connections = sessions_.size();
    }
    notify_if_all_closed();
  }
  bool trust(const std::shared_ptr<Session>& session) override {
    if (door_.trust(session->ticket)) return true;
    count_full();
    return false;
  }
  void count_request(std::span<const std::uint8_t> pdu) override {
    if (options_.traffic != nullptr) options_.traffic->count_request(pdu);
    std::lock_guard lock(stats_mutex_);
    ++stats_.requests;
  }
  void count_response(std::span<const std::uint8_t> pdu) override {
    if (options_.traffic != nullptr) options_.traffic->count_response(pdu);
  }
  void count_bad_header() override {
    std::lock_guard lock(stats_mutex_);
    ++stats_.bad_headers;
  }
  void count_idle_close() override {
    std::lock_guard lock(stats_mutex_);
    ++stats_.idle_closed;
  }

 private:
  void accept() {
    acceptor_.async_accept([self = shared_from_this()](const boost::system::error_code& error, tcp::socket socket) {
      self->on_accept(error, std::move(socket));
    });
  }

  void on_accept(const boost::system::error_code& error, tcp::socket socket) {
    if (!acceptor_.is_open()) return;
    if (error) {
      if (error == asio::error::operation_aborted) return;
      // Out of descriptors and the like: wait a moment instead of spinning on the error.
      spdlog::warn("{}: accepting a connection failed: {}; retrying in 100 ms", log_prefix(), error.message());
      retry_timer_.expires_after(std::chrono::milliseconds{100});
      retry_timer_.async_wait([self = shared_from_this()](const boost::system::error_code& wait_error) {
        if (!wait_error) self->accept();
      });
      return;
    }
    if (!allowed(socket)) {
      deny(std::move(socket));
      accept();
      return;
    }
    const std::string address = address_of(socket);
    std::shared_ptr<Session> session;
    if (options_.tls != nullptr) {
      auto context = options_.tls->context();  // the one loaded last (SIGHUP reloads it)
      session = std::make_shared<TlsSession>(asio::ssl::stream<tcp::socket>(std::move(socket), *context),
                                             shared_from_this(), context);
    } else {
      session = std::make_shared<PlainSession>(std::move(socket), shared_from_this());
    }
    const auto ticket = door_.admit(address, session);
    if (!ticket) {
      count_full();
      session->close_by_door();  // never started: the socket closes, nothing is answered
    } else {
      session->ticket = *ticket;
      sessions_.insert(session);
      {
        std::lock_guard lock(stats_mutex_);
        ++stats_.accepted;
        stats_.open_connections = sessions_.size();
      }
      spdlog::debug("{}: {} connected ({} open)", log_prefix(), session->peer(), sessions_.size());
      session->start();
    }
    accept();
  }

  // Over modbus_tcp.max_connections: the door has logged it once per episode.
  void count_full() {
    std::lock_guard lock(stats_mutex_);
    ++stats_.refused;
    ++stats_.refusals[listener_index()].max_connections;
  }

  std::size_t listener_index() const { return options_.tls != nullptr ? 1 : 0; }
  std::string_view log_prefix() const { return options_.tls != nullptr ? "modbus tcp security" : "modbus tcp"; }

  static std::string address_of(const tcp::socket& socket) {
    boost::system::error_code error;
    const auto peer = socket.remote_endpoint(error);
    return error ? std::string("(unknown peer)") : peer.address().to_string();
  }

  static IpAddress client_address(const tcp::endpoint& peer) {
    const auto address = peer.address();
    if (address.is_v4()) return IpAddress::v4(address.to_v4().to_bytes());
    return IpAddress::v6(address.to_v6().to_bytes());
  }

  bool allowed(const tcp::socket& socket) const {
    if (!access_.restricted()) return true;
    boost::system::error_code error;
    const auto peer = socket.remote_endpoint(error);
    return !error && access_.allows(client_address(peer));  // a peer already gone is not let in either
  }

  // Not in modbus_tcp.allow: closed without a Modbus answer, as if nothing listened.
  void deny(tcp::socket socket) {
    door_.count_denied();
    {
      std::lock_guard lock(stats_mutex_);
      ++stats_.denied;
      ++stats_.refusals[listener_index()].allow;
    }
    boost::system::error_code ignored;
    const auto peer = socket.remote_endpoint(ignored);
    const std::string address = peer.address().to_string();
    // Each address is logged once (a client retrying in a loop must not flood the log); the
    // set is bounded so a scan of many addresses cannot grow it without limit.
    if (denial_logged_.size() < kMaxDenialsLogged && denial_logged_.insert(address).second) {
      spdlog::warn(
          "modbus tcp: refusing connection from {}: not in modbus_tcp.allow ({}); further refusals of this "
          "address are counted, not logged",
          address, access_.describe());
    }
    socket.shutdown(tcp::socket::shutdown_both, ignored);
    socket.close(ignored);
  }

  void stop_accepting() {
    boost::system::error_code ignored;
    acceptor_.close(ignored);
    retry_timer_.cancel();
    door_.close();
  }

  void notify_if_all_closed() {
    if (!sessions_.empty() || !on_all_closed_) return;
    asio::post(io_, std::exchange(on_all_closed_, nullptr));
  }

  asio::io_context& io_;
  const TcpServerOptions options_;
  RequestHandler& handler_;
  const AccessPolicy access_;
  Door door_;
  static constexpr std::size_t kMaxDenialsLogged = 256;
  std::set<std::string> denial_logged_;
  tcp::acceptor acceptor_;
  asio::steady_timer retry_timer_;
  std::uint16_t port_ = 0;
  std::set<std::shared_ptr<Session>> sessions_;
  std::function<void()> on_all_closed_;

  mutable std::mutex stats_mutex_;  // stats() is read from other threads (gateway unit, tests)
  TcpServerStats stats_;
};

TcpServer::TcpServer(asio::io_context& io, TcpServerOptions options, RequestHandler& handler)
    : impl_(std::make_shared<Impl>(io, std::move(options), handler)) {}

TcpServer::~TcpServer() {
  // A destructor must not throw: a failure to close is logged (the sockets close with the process).
  try {
    impl_->close_all();
  } catch (const std::exception& error) {
    spdlog::error("modbus: closing the connections failed: {}", error.what());
  }
}

void TcpServer::start() { impl_->start(); }
std::uint16_t TcpServer::port() const { return impl_->port(); }
void TcpServer::shutdown(std::function<void()> done) { impl_->shutdown(std::move(done)); }
void TcpServer::close_all() { impl_->close_all(); }
TcpServerStats TcpServer::stats() const { return impl_->stats(); }
DoorStats TcpServer::door_stats() const { return impl_->door_stats(); }
std::string_view TcpServer::listener_name() const {
  return impl_->options().tls != nullptr ? kListenerNames[1] : kListenerNames[0];
}

}  // namespace sms::gateway
