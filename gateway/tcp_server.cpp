#include "gateway/tcp_server.h"

#include <atomic>
#include <mutex>
#include <set>
#include <stdexcept>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <spdlog/spdlog.h>

#include "gateway/mbap_session.h"

namespace sms::gateway {

namespace asio = boost::asio;
using asio::ip::tcp;

class TcpServer::Impl : public SessionHost, public std::enable_shared_from_this<TcpServer::Impl> {
 public:
  Impl(asio::io_context& io, TcpServerOptions options, RequestHandler& handler)
      : io_(io), options_(std::move(options)), handler_(handler), acceptor_(io), retry_timer_(io) {}

  void start() {
    const tcp::endpoint endpoint = resolve();
    const std::string where = options_.host + ":" + std::to_string(options_.port);
    boost::system::error_code error;
    acceptor_.open(endpoint.protocol(), error);
    if (!error) acceptor_.set_option(tcp::acceptor::reuse_address(true), error);
    if (!error) acceptor_.bind(endpoint, error);
    if (!error) acceptor_.listen(asio::socket_base::max_listen_connections, error);
    if (error) {
      std::string advice;
      if (error == asio::error::address_in_use) {
        advice = "; another program (another sms-gateway?) is listening there: stop it, or choose a free port with "
                 "--listen HOST:PORT or modbus_tcp.listen in the configuration";
      } else if (error == asio::error::access_denied) {
        advice = "; ports below 1024 need root or CAP_NET_BIND_SERVICE: run with that capability, or listen on a "
                 "port above 1023 (e.g. --listen " + options_.host + ":5020)";
      } else if (error == boost::system::errc::address_not_available) {
        advice = "; no network interface of this machine has that address: use 0.0.0.0 (every interface), "
                 "127.0.0.1, or an address this machine owns";
      }
      acceptor_.close(error);
      throw std::runtime_error("cannot listen for Modbus TCP on " + where + ": " + error.message() + advice);
    }
    port_ = acceptor_.local_endpoint().port();
    spdlog::info("modbus tcp: listening on {}:{} (at most {} connections, idle timeout {})", options_.host, port_,
                 options_.max_connections,
                 options_.idle_timeout.count() > 0 ? duration_text(options_.idle_timeout) : std::string("off"));
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
  void on_session_closed(const std::shared_ptr<MbapSession>& session) override {
    if (sessions_.erase(session) == 0) return;
    spdlog::debug("modbus tcp: {} disconnected ({} open)", session->peer(), sessions_.size());
    {
      std::lock_guard lock(stats_mutex_);
      stats_.open_connections = sessions_.size();
    }
    if (sessions_.size() < options_.max_connections) refusal_logged_ = false;
    notify_if_all_closed();
  }
  void count_request() override {
    std::lock_guard lock(stats_mutex_);
    ++stats_.requests;
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
  tcp::endpoint resolve() {
    boost::system::error_code error;
    const auto address = asio::ip::make_address(options_.host, error);
    if (!error) return {address, options_.port};
    tcp::resolver resolver(io_);
    const auto results = resolver.resolve(options_.host, std::to_string(options_.port), error);
    if (error || results.empty()) {
      throw std::runtime_error("cannot listen for Modbus TCP on " + options_.host + ":" + std::to_string(options_.port) +
                               ": the host does not resolve (" + error.message() +
                               "); give an IP address such as 0.0.0.0 or 127.0.0.1");
    }
    return results.begin()->endpoint();
  }

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
    if (sessions_.size() >= options_.max_connections) {
      refuse(std::move(socket));
    } else {
      auto session = std::make_shared<MbapSession>(std::move(socket), shared_from_this());
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
    {
      std::lock_guard lock(stats_mutex_);
      ++stats_.refused;
    }
    boost::system::error_code ignored;
    const auto peer = socket.remote_endpoint(ignored);
    // Logged once per episode: a client retrying in a loop must not flood the log.
    if (!refusal_logged_) {
      spdlog::warn("modbus tcp: refusing connection from {}: {} connections open, the limit "
                   "(modbus_tcp.max_connections); further refusals are counted, not logged",
                   peer.address().to_string(), options_.max_connections);
      refusal_logged_ = true;
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
  tcp::acceptor acceptor_;
  asio::steady_timer retry_timer_;
  std::uint16_t port_ = 0;
  std::set<std::shared_ptr<MbapSession>> sessions_;
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

TcpServer::~TcpServer() { impl_->close_all(); }

void TcpServer::start() { impl_->start(); }
std::uint16_t TcpServer::port() const { return impl_->port(); }
void TcpServer::shutdown(std::function<void()> done) { impl_->shutdown(std::move(done)); }
void TcpServer::close_all() { impl_->close_all(); }
TcpServerStats TcpServer::stats() const { return impl_->stats(); }

}  // namespace sms::gateway
