#include "gateway/observability/metrics_server.h"

#include <optional>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>

#include <spdlog/spdlog.h>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/beast/core/error.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/empty_body.hpp>
#include <boost/beast/http/error.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/beast/http/write.hpp>

#include "gateway/net/door.h"
#include "gateway/net/listener.h"

namespace sms::gateway {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using asio::ip::tcp;

namespace {

constexpr std::string_view kTextContentType = "text/plain; charset=utf-8";
constexpr std::string_view kServerName = "sms-gateway/" SMS_GATEWAY_VERSION;

struct Answer {
  http::status status = http::status::ok;
  std::string_view content_type = kTextContentType;
  std::string body;
  bool allow_header = false;  // 405: say which methods the path takes
};

Answer text_answer(http::status status, std::string body) { return Answer{status, kTextContentType, std::move(body)}; }

// The endpoints, as data: path and what it answers.
struct Endpoint {
  std::string_view path;
  Answer (*answer)(const MetricsServer::SnapshotFn& snapshot);
};

constexpr Endpoint kEndpoints[] = {
    {"/metrics",
     [](const MetricsServer::SnapshotFn& snapshot) {
       return Answer{http::status::ok, kPrometheusContentType, render_prometheus(snapshot())};
     }},
    {"/healthz",
     [](const MetricsServer::SnapshotFn& snapshot) {
       const Health health = health_of(snapshot());
       return text_answer(health.ok ? http::status::ok : http::status::service_unavailable, health.reason + "\n");
     }},
};

Answer answer_for(http::verb method, std::string_view target, const MetricsServer::SnapshotFn& snapshot) {
  const std::string_view path = target.substr(0, target.find('?'));
  for (const auto& endpoint : kEndpoints) {
    if (endpoint.path != path) continue;
    if (method != http::verb::get && method != http::verb::head) {
      Answer answer = text_answer(http::status::method_not_allowed, "use GET or HEAD\n");
      answer.allow_header = true;
      return answer;
    }
    try {
      return endpoint.answer(snapshot);
    } catch (const std::exception& error) {
      spdlog::error("metrics: {} failed: {}", path, error.what());
      return text_answer(http::status::internal_server_error, std::string(error.what()) + "\n");
    }
  }
  return text_answer(http::status::not_found, "not found; try /metrics or /healthz\n");
}

beast::string_view beast_view(std::string_view text) { return {text.data(), text.size()}; }

// The answer to a request that could not be read; nullopt: just close (timeout, client gone,
// connection closed between requests, server stopping).
std::optional<Answer> answer_for_read_error(const beast::error_code& error) {
  if (error == http::error::end_of_stream || error == http::error::partial_message) return std::nullopt;
  if (error == http::error::header_limit) {
    return text_answer(http::status::request_header_fields_too_large, "request headers too large\n");
  }
  if (error == http::error::unexpected_body || error == http::error::body_limit) {
    return text_answer(http::status::payload_too_large, "requests here carry no body\n");
  }
  if (error.category() == http::make_error_code(http::error::bad_method).category()) {
    return text_answer(http::status::bad_request, "not an HTTP/1.1 request: " + error.message() + "\n");
  }
  return std::nullopt;
}

}  // namespace

class MetricsSession;

static DoorSettings door_settings(const MetricsServerOptions& options) {
  return {"metrics", "metrics", "complete HTTP request", options.door, fixed_limit_names("the metrics endpoint"),
          nullptr};
}

class MetricsServer::Impl {
 public:
  Impl(MetricsServerOptions options, SnapshotFn snapshot)
      : options_(std::move(options)),
        snapshot_(std::move(snapshot)),
        acceptor_(io_),
        retry_timer_(io_),
        door_(io_, door_settings(options_)) {}

  ~Impl() { stop(); }

  void start() {
    if (started_) throw std::logic_error("MetricsServer::start called twice");
    started_ = true;
    open_listener(acceptor_, options_.listen.host, options_.listen.port,
                  {"serve metrics", "--metrics HOST:PORT or logging.metrics_listen", 9102});
    port_ = acceptor_.local_endpoint().port();
    spdlog::info("metrics: serving /metrics and /healthz on http://{} ({})",
                 config::HostPort{options_.listen.host, port_}.to_string(), door_.describe());
    accept();
    thread_ = std::thread([this] { io_.run(); });
  }

  void stop() {
    close_and_join(io_, thread_, [this] { close_all(); });
  }

  std::uint16_t port() const { return port_; }

  // For sessions (io thread only).
  const MetricsServerOptions& options() const { return options_; }
  // The gateway's figures, with this listener's own door.
  MetricsSnapshot snapshot_with_door() const {
    MetricsSnapshot snapshot = snapshot_();
    snapshot.listeners.push_back({"metrics", door_.stats()});
    return snapshot;
  }
  Door& door() { return door_; }
  void add(MetricsSession* session) { sessions_.insert(session); }
  void remove(MetricsSession* session) { sessions_.erase(session); }

 private:
  void accept();
  void close_all();

  const MetricsServerOptions options_;
  const SnapshotFn snapshot_;
  bool started_ = false;
  std::uint16_t port_ = 0;
  // Declared before io_: sessions destroyed with io_'s pending handlers still unregister here.
  std::set<MetricsSession*> sessions_;
  asio::io_context io_;
  tcp::acceptor acceptor_;
  asio::steady_timer retry_timer_;
  // After io_: destroyed first, once stop() has closed every session (a session leaves the door in
  // close(), never in its destructor, which may run when io_ is destroyed).
  Door door_;
  std::thread thread_;
};

// One HTTP connection: read a request, answer it, and again while the client keeps it alive.
class MetricsSession final : public std::enable_shared_from_this<MetricsSession>, public DoorGuest {
 public:
  MetricsSession(tcp::socket socket, MetricsServer::Impl& server)
      : stream_(std::move(socket)), server_(server), buffer_(server.options().max_request_bytes) {
    beast::error_code error;
    const auto endpoint = stream_.socket().remote_endpoint(error);
    address_ = error ? std::string("(unknown peer)") : endpoint.address().to_string();
    peer_ = error ? address_ : address_ + ":" + std::to_string(endpoint.port());
    server_.add(this);
  }
  ~MetricsSession() { server_.remove(this); }

  // false: the door refused it (the served budget is full); it is closed.
  bool start() {
    const auto ticket = server_.door().admit(address_, weak_from_this());
    if (!ticket) {
      close();
      return false;
    }
    ticket_ = *ticket;
    read();
    return true;
  }

  void close() {
    if (closed_) return;
    closed_ = true;
    server_.door().leave(ticket_);
    beast::error_code ignored;
    stream_.socket().shutdown(tcp::socket::shutdown_both, ignored);
    stream_.close();
  }

  // DoorGuest
  void close_by_door() override { close(); }
  bool silent() const override {
    if (buffer_.size() > 0) return false;
    beast::error_code error;
    return const_cast<beast::tcp_stream&>(stream_).socket().available(error) == 0 || error;
  }
  const std::string& peer() const override { return peer_; }

 private:
  void read() {
    parser_.emplace();
    parser_->header_limit(static_cast<std::uint32_t>(server_.options().max_request_bytes));
    parser_->body_limit(0);
    stream_.expires_after(server_.options().request_timeout);
    http::async_read(
        stream_, buffer_, *parser_,
        [self = shared_from_this()](const beast::error_code& error, std::size_t) { self->on_read(error); });
  }

  void on_read(const beast::error_code& error) {
    if (error) {
      // Timeouts, clients leaving, or a stop(): nothing to answer.
      if (auto answer = answer_for_read_error(error)) {
        spdlog::debug("metrics: bad request: {}", error.message());
        write(std::move(*answer), false, 11, false);
      } else {
        close();
      }
      return;
    }
    // A complete request: the client is served from now on (nothing here needs a login).
    if (!server_.door().trust(ticket_)) {
      close();
      return;
    }
    const auto& request = parser_->get();
    const bool head = request.method() == http::verb::head;
    const std::string_view target(request.target().data(), request.target().size());
    const MetricsServer::SnapshotFn snapshot = [&server = server_] { return server.snapshot_with_door(); };
    write(answer_for(request.method(), target, snapshot), request.keep_alive(), request.version(), head);
  }

  void write(Answer answer, bool keep_alive, unsigned version, bool head) {
    response_.emplace(answer.status, version);
    response_->set(http::field::server, beast_view(kServerName));
    response_->set(http::field::content_type, beast_view(answer.content_type));
    response_->set(http::field::cache_control, "no-store");
    if (answer.allow_header) response_->set(http::field::allow, "GET, HEAD");
    response_->keep_alive(keep_alive);
    response_->content_length(answer.body.size());
    if (!head) response_->body() = std::move(answer.body);
    stream_.expires_after(server_.options().request_timeout);
    http::async_write(stream_, *response_,
                      [self = shared_from_this(), keep_alive](const beast::error_code& error, std::size_t) {
                        self->on_written(error, keep_alive);
                      });
  }

  void on_written(const beast::error_code& error, bool keep_alive) {
    response_.reset();
    if (error || !keep_alive) {
      close();
      return;
    }
    read();
  }

  beast::tcp_stream stream_;
  MetricsServer::Impl& server_;
  std::string address_;
  std::string peer_;
  Door::Ticket ticket_ = 0;
  bool closed_ = false;
  beast::flat_buffer buffer_;
  std::optional<http::request_parser<http::empty_body>> parser_;
  std::optional<http::response<http::string_body>> response_;
};

void MetricsServer::Impl::accept() {
  acceptor_.async_accept([this](const beast::error_code& error, tcp::socket socket) {
    if (!acceptor_.is_open()) return;
    if (!error) {
      std::make_shared<MetricsSession>(std::move(socket), *this)->start();
    } else if (error == asio::error::operation_aborted) {
      return;
    } else {
      // Out of descriptors and the like: wait a moment instead of spinning on the error.
      spdlog::warn("metrics: accepting a connection failed: {}; retrying in 100 ms", error.message());
      retry_timer_.expires_after(std::chrono::milliseconds{100});
      retry_timer_.async_wait([this](const beast::error_code& wait_error) {
        if (!wait_error) accept();
      });
      return;
    }
    accept();
  });
}

void MetricsServer::Impl::close_all() {
  beast::error_code ignored;
  acceptor_.close(ignored);
  retry_timer_.cancel();
  door_.close();
  const auto sessions = sessions_;
  for (auto* session : sessions) session->close();
}

MetricsServer::MetricsServer(MetricsServerOptions options, SnapshotFn snapshot)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(snapshot))) {}
MetricsServer::~MetricsServer() = default;

void MetricsServer::start() { impl_->start(); }
void MetricsServer::stop() { impl_->stop(); }
std::uint16_t MetricsServer::port() const { return impl_->port(); }

}  // namespace sms::gateway
