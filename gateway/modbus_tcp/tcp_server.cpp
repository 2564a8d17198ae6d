#include "gateway/modbus_tcp/tcp_server.h"

#include <algorithm>
#include <atomic>
#include <list>
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
#include "gateway/modbus_tcp/listener.h"
#include "gateway/modbus_tcp/mbap_session.h"
#include "gateway/modbus_tcp/tls.h"
#include "gateway/modbus_tcp/traffic_counters.h"

namespace sms::gateway {

namespace asio = boost::asio;
using asio::ip::tcp;

class TcpServer::Impl final : public SessionHost, public std::enable_shared_from_this<TcpServer::Impl> {
 public:
  Impl(asio::io_context& io, TcpServerOptions options, RequestHandler& handler)
      : io_(io),
        options_(std::move(options)),
        handler_(handler),
        access_(options_.allow),
        acceptor_(io),
        retry_timer_(io) {}

  void start() {
    if (options_.tls != nullptr) {
      open_listener(acceptor_, options_.host, options_.port,
                    {"listen for Modbus/TCP Security", "modbus_tcp.tls.listen in the configuration", 8020});
      port_ = acceptor_.local_endpoint().port();
      const config::TlsConfig& tls = options_.tls->settings();
      spdlog::info(
          "modbus tcp security: listening on {}:{} (TLS 1.2/1.3, client certificates of CA {} required; at "
          "most {} connections served, idle timeout {}; at most {} handshakes at once, {} per client "
          "address, each within {}; clients allowed: {})",
          options_.host, port_, tls.ca, options_.max_connections,
          options_.idle_timeout.count() > 0 ? duration_text(options_.idle_timeout) : std::string("off"),
          tls.max_handshakes, tls.max_handshakes_per_address, duration_text(tls.handshake_timeout), access_.describe());
      accept();
      return;
    }
    open_listener(acceptor_, options_.host, options_.port,
                  {"listen for Modbus TCP", "--listen HOST:PORT or modbus_tcp.listen in the configuration", 5020});
    port_ = acceptor_.local_endpoint().port();
    spdlog::info("modbus tcp: listening on {}:{} (at most {} connections, idle timeout {}, clients allowed: {})",
                 options_.host, port_, options_.max_connections,
                 options_.idle_timeout.count() > 0 ? duration_text(options_.idle_timeout) : std::string("off"),
                 access_.describe());
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

  // SessionHost
  RequestHandler& handler() override { return handler_; }
  const TcpServerOptions& options() const override { return options_; }
  TlsService* tls() override { return options_.tls; }
  void on_session_closed(const std::shared_ptr<Session>& session) override {
    forget_handshake(session);
    if (sessions_.erase(session) == 0) return;
    spdlog::debug("modbus tcp: {} disconnected ({} open)", session->peer(), sessions_.size());
    {
      std::lock_guard lock(stats_mutex_);
      stats_.open_connections = sessions_.size();
    }
    if (served_count() < options_.max_connections) refusal_logged_ = false;
    notify_if_all_closed();
  }
  bool handshake_done(const std::shared_ptr<Session>& session) override {
    forget_handshake(session);
    if (served_count() <= options_.max_connections) return true;
    // Handshakes that began while slots were free finished after the last one was taken.
    count_refusal(session->peer());
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
      spdlog::warn("modbus tcp: accepting a connection failed: {}; retrying in 100 ms", error.message());
      retry_timer_.expires_after(std::chrono::milliseconds{100});
      retry_timer_.async_wait([self = shared_from_this()](const boost::system::error_code& wait_error) {
        if (!wait_error) self->accept();
      });
      return;
    }
    if (!allowed(socket)) {
      deny(std::move(socket));
    } else if (served_count() >= options_.max_connections) {
      refuse(std::move(socket));
    } else {
      std::shared_ptr<Session> session;
      if (options_.tls != nullptr) {
        const std::string address = address_of(socket);
        make_room_for_handshake(address);
        auto context = options_.tls->context();  // the one loaded last (SIGHUP reloads it)
        session = std::make_shared<TlsSession>(asio::ssl::stream<tcp::socket>(std::move(socket), *context),
                                               shared_from_this(), context);
        handshaking_.push_back(Handshake{session, address});
      } else {
        session = std::make_shared<PlainSession>(std::move(socket), shared_from_this());
      }
      sessions_.insert(session);
      {
        std::lock_guard lock(stats_mutex_);
        ++stats_.accepted;
        stats_.open_connections = sessions_.size();
      }
      spdlog::debug("modbus tcp: {} connected ({} open)", session->peer(), sessions_.size());
      session->start();
    }
    accept();
  }

  void refuse(tcp::socket socket) {
    count_refusal(address_of(socket));
    boost::system::error_code ignored;
    socket.shutdown(tcp::socket::shutdown_both, ignored);
    socket.close(ignored);
  }

  void count_refusal(const std::string& client) {
    {
      std::lock_guard lock(stats_mutex_);
      ++stats_.refused;
      ++stats_.refusals[listener_index()].max_connections;
    }
    // Logged once per episode: a client retrying in a loop must not flood the log.
    if (!refusal_logged_) {
      spdlog::warn(
          "{}: refusing connection from {}: {} connections {}, the limit (modbus_tcp.max_connections); "
          "further refusals are counted, not logged",
          log_prefix(), client, options_.max_connections, options_.tls != nullptr ? "served" : "open");
      refusal_logged_ = true;
    }
  }

  // Connections served: on the TLS listener those past the handshake (an unauthenticated client
  // cannot take a slot of an authenticated one).
  std::size_t served_count() const { return sessions_.size() - handshaking_.size(); }

  // Before a new handshake starts: when its client address, or the listener, has the most
  // handshakes it may have, the oldest of them is closed (a silent one first, one that sent
  // nothing yet). Evicting rather than refusing means connections that sit in the handshake
  // cannot keep a newer client, one with a certificate, from being served: the newcomer's
  // handshake only has to finish before `max_handshakes` (or per address) newer ones arrive.
  void make_room_for_handshake(const std::string& address) {
    const config::TlsConfig& tls = options_.tls->settings();
    const auto from_address = static_cast<std::size_t>(std::count_if(
        handshaking_.begin(), handshaking_.end(), [&](const Handshake& h) { return h.address == address; }));
    std::optional<std::string> only;
    std::string_view limit;
    if (from_address >= tls.max_handshakes_per_address) {
      only = address;
      limit = "modbus_tcp.tls.max_handshakes_per_address";
    } else if (handshaking_.size() >= tls.max_handshakes) {
      limit = "modbus_tcp.tls.max_handshakes";
    } else {
      return;
    }
    const Handshake* oldest = nullptr;
    const Handshake* oldest_silent = nullptr;
    for (const auto& handshake : handshaking_) {
      if (only && handshake.address != *only) continue;
      if (oldest == nullptr) oldest = &handshake;
      if (oldest_silent == nullptr && handshake.session->silent()) oldest_silent = &handshake;
    }
    const Handshake* victim = oldest_silent != nullptr ? oldest_silent : oldest;
    if (victim == nullptr) return;
    const std::shared_ptr<Session> session = victim->session;  // close() erases the entry
    options_.tls->handshake_evicted();
    ++evictions_unlogged_;
    const auto now = std::chrono::steady_clock::now();
    // Once per 10 s at most: this is what a flood of connections looks like.
    if (now - eviction_logged_at_ >= kEvictionLogInterval) {
      spdlog::warn(
          "modbus tcp security: closing {} in the TLS handshake{} to make room for a new connection from {} "
          "({} reached) [evicted]; {} such closing(s) since the last line",
          session->peer(), oldest_silent != nullptr ? " (silent so far)" : "", address, limit, evictions_unlogged_);
      eviction_logged_at_ = now;
      evictions_unlogged_ = 0;
    }
    session->close();
  }

  void forget_handshake(const std::shared_ptr<Session>& session) {
    const auto found = std::find_if(handshaking_.begin(), handshaking_.end(),
                                    [&](const Handshake& h) { return h.session == session; });
    if (found != handshaking_.end()) handshaking_.erase(found);
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
  }

  void notify_if_all_closed() {
    if (!sessions_.empty() || !on_all_closed_) return;
    asio::post(io_, std::exchange(on_all_closed_, nullptr));
  }

  asio::io_context& io_;
  const TcpServerOptions options_;
  RequestHandler& handler_;
  const AccessPolicy access_;
  static constexpr std::size_t kMaxDenialsLogged = 256;
  std::set<std::string> denial_logged_;
  tcp::acceptor acceptor_;
  asio::steady_timer retry_timer_;
  std::uint16_t port_ = 0;
  std::set<std::shared_ptr<Session>> sessions_;
  // TLS: the sessions of sessions_ still in the handshake, oldest first, with their client address.
  struct Handshake {
    std::shared_ptr<Session> session;
    std::string address;
  };
  std::list<Handshake> handshaking_;
  static constexpr std::chrono::seconds kEvictionLogInterval{10};
  std::chrono::steady_clock::time_point eviction_logged_at_{};
  std::uint64_t evictions_unlogged_ = 0;
  bool refusal_logged_ = false;
  std::function<void()> on_all_closed_;

  mutable std::mutex stats_mutex_;  // stats() is read from other threads (gateway unit, tests)
  TcpServerStats stats_;
};

std::string duration_text(std::chrono::milliseconds duration) {
  if (duration.count() % 1000 == 0) return std::to_string(duration.count() / 1000) + " s";
  return std::to_string(duration.count()) + " ms";
}

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

}  // namespace sms::gateway
