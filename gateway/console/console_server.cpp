#include "gateway/console/console_server.h"

#include <openssl/ssl.h>

#include <deque>
#include <fstream>
#include <set>
#include <sstream>
#include <stdexcept>
#include <thread>

#include <spdlog/spdlog.h>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>
#include <boost/beast/websocket/ssl.hpp>

#include "gateway/console/console_commission.h"
#include "gateway/console/console_routes.h"
#include "gateway/console/console_tls.h"
#include "gateway/console/console_view.h"
#include "gateway/console/web_assets.h"
#include "gateway/modbus_tcp/tls.h"
#include "gateway/net/door.h"
#include "gateway/net/listener.h"
#include "gateway/service/access_gate.h"
#include "gateway/service/modbus_request.h"

namespace sms::gateway::console {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
namespace ssl = asio::ssl;
using asio::ip::tcp;

namespace {

constexpr std::string_view kCookieName = "sms_console";
constexpr std::string_view kServerName = "sms-gateway/" SMS_GATEWAY_VERSION " console";
// Pages load scripts and styles from this server only; nothing inline, no framing by other sites.
constexpr std::string_view kContentSecurityPolicy =
    "default-src 'self'; img-src 'self' data:; connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; "
    "form-action 'self'";
// A slow page that lets this many pushes pile up is closed (it reconnects by itself).
constexpr std::size_t kMaxQueuedMessages = 64;

beast::string_view view(std::string_view text) { return {text.data(), text.size()}; }
std::string_view view(beast::string_view text) { return {text.data(), text.size()}; }

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

// Where the Modbus answers of the console's requests come back: the console's io_context while
// it runs; dropped after stop() (the work itself still happened).
struct Mailbox {
  std::mutex mutex;
  asio::io_context* io = nullptr;
  void post(std::function<void()> work) {
    std::lock_guard lock(mutex);
    if (io != nullptr) asio::post(*io, std::move(work));
  }
  void close() {
    std::lock_guard lock(mutex);
    io = nullptr;
  }
};

ModbusAnswer answer_of(Bytes pdu) {
  ModbusAnswer answer;
  if (pdu.empty()) {
    answer.exception = 0xFF;
    answer.message = "no answer";
  } else if ((pdu[0] & 0x80) != 0 && pdu.size() >= 2) {
    answer.exception = pdu[1];
    answer.message = exception_text(pdu[1]);
  }
  answer.pdu = std::move(pdu);
  return answer;
}

class ConsoleReply final : public Reply::Target {
 public:
  ConsoleReply(std::shared_ptr<Mailbox> mailbox, std::function<void(ModbusAnswer)> done)
      : mailbox_(std::move(mailbox)), done_(std::move(done)) {}
  void deliver(std::uint64_t, Bytes response_pdu) override {
    mailbox_->post([done = done_, pdu = std::move(response_pdu)]() mutable { done(answer_of(std::move(pdu))); });
  }

 private:
  std::shared_ptr<Mailbox> mailbox_;
  std::function<void(ModbusAnswer)> done_;
};

struct Peer {
  bool loopback = false;
  std::string address;
  std::optional<Principal> certificate;  // HTTPS with a client certificate that has a role
  Door::Ticket ticket = 0;               // the connection's, at the console's door
  bool over_budget = false;              // it could not be trusted: answered 503, then closed
};

DoorSettings door_settings(const ConsoleLimits& limits) {
  return {"console", "console", "complete HTTP request", limits.door, fixed_limit_names("the console"), nullptr};
}

}  // namespace

// Something open the server closes on stop().
class Connection {
 public:
  virtual ~Connection() = default;
  virtual void close() = 0;
};
// An open WebSocket, stepped by the server's timer.
class Socket : public Connection {
 public:
  virtual void tick(SteadyClock::time_point now, bool push) = 0;
};

class ConsoleServer::Impl final : public Services {
 public:
  Impl(config::ConsoleConfig settings, ConsoleBackend backend, ConsoleLimits limits)
      : settings_(std::move(settings)),
        backend_(std::move(backend)),
        limits_(limits),
        rules_(access_rules(settings_)),
        gate_(backend_.policy != nullptr ? *backend_.policy : throw std::invalid_argument("console: no role policy"),
              "console"),
        sessions_(settings_.session_timeout),
        commissioning_(*backend_.config, backend_.lending),
        acceptor_(io_),
        timer_(io_),
        mailbox_(std::make_shared<Mailbox>()),
        logins_(settings_, [mailbox = mailbox_](std::function<void()> work) { mailbox->post(std::move(work)); }),
        door_(io_, door_settings(limits_)) {
    if (backend_.safety == nullptr) throw std::invalid_argument("console: no safety rules for the jog panel");
  }

  ~Impl() override { stop(); }

  void start() {
    if (settings_.tls) {
      if (!backend_.config->modbus_tcp.tls) throw std::runtime_error("console.tls needs modbus_tcp.tls");
      ssl_ = make_tls_context(*backend_.config->modbus_tcp.tls);
      // With users a browser without a certificate may still log in with a password.
      if (rules_.users) ssl_->set_verify_mode(ssl::verify_peer);
    } else if (!settings_.certificate.empty()) {
      ssl_ = console_tls_context(settings_.certificate, settings_.key);
    }
    try {
      open_listener(acceptor_, settings_.listen.host, settings_.listen.port,
                    {"serve the browser console", "--console HOST:PORT or console.listen", 8080});
    } catch (const std::runtime_error& error) {
      if (!settings_.any_port_if_taken) throw;
      spdlog::warn("console: {}; serving it on a free port instead", error.what());
      beast::error_code ignored;
      acceptor_.close(ignored);
      open_listener(acceptor_, settings_.listen.host, 0,
                    {"serve the browser console", "--console HOST:PORT or console.listen", 8080});
    }
    port_ = acceptor_.local_endpoint().port();
    if (std::ifstream chart{std::string(kChartJsPath), std::ios::binary}) {
      std::ostringstream text;
      text << chart.rdbuf();
      chart_js_ = text.str();
    } else {
      spdlog::warn("console: {} is missing: the plots stay empty (install the Debian package libjs-chart.js)",
                   kChartJsPath);
    }
    mailbox_->io = &io_;
    spdlog::info("console: serving the browser console on {} ({}; {})", url(), access_summary(), door_.describe());
    if (settings_.insecure_http && rules_.users && !config::is_loopback_host(settings_.listen.host)) {
      spdlog::warn(
          "console: passwords of console.users cross the network in clear: {} is plain HTTP on a non-loopback "
          "address (console.insecure_http: true); give the console a certificate and key (console.certificate, "
          "console.key) and remove insecure_http",
          url());
    }
    accept();
    schedule_tick();
    thread_ = std::thread([this] { io_.run(); });
  }

  void stop() {
    // The mailbox closes once every session is closed: no Modbus answer is posted after that.
    close_and_join(io_, thread_, [this] {
      close_all();
      mailbox_->close();
    });
    // After the console thread: a check finishing now posts into the closed mailbox.
    logins_.stop();
  }

  std::uint16_t port() const { return port_; }
  LoginStats login_stats() const { return logins_.stats(); }
  std::string url() const {
    return std::string(settings_.https() ? "https" : "http") + "://" +
           config::HostPort{settings_.listen.host, port_}.to_string() + "/";
  }

  // --- Services -------------------------------------------------------------------------------
  const config::Config& config() const override { return *backend_.config; }
  const config::ConsoleConfig& settings() const override { return settings_; }
  const UnitRouter& units() const override { return *backend_.units; }
  std::shared_ptr<WireMonitor> monitor(std::string_view bus) const override {
    return backend_.monitor ? backend_.monitor(bus) : nullptr;
  }
  SessionStore& sessions() override { return sessions_; }
  Commissioning& commissioning() override { return commissioning_; }

  const nlohmann::json& overview() override {
    const auto now = SteadyClock::now();
    if (overview_.is_null() || now - overview_at_ >= kPushPeriod / 2) {
      overview_ = overview_json(*backend_.config, backend_.metrics(), *backend_.units);
      overview_at_ = now;
    }
    return overview_;
  }

  std::string session_cookie(const std::string& token) const override {
    std::string cookie = std::string(kCookieName) + "=" + token + "; Path=/; HttpOnly; SameSite=Strict";
    if (settings_.https()) cookie += "; Secure";
    if (token.empty()) cookie += "; Max-Age=0";
    return cookie;
  }

  void modbus(const Principal& who, std::uint8_t unit, Bytes pdu, std::function<void(ModbusAnswer)> done) override {
    submit(who, unit, std::move(pdu), std::move(done), std::nullopt);
  }

  std::optional<GateRefusal> refusal(const Principal& who, std::uint8_t unit,
                                     std::span<const std::uint8_t> pdu) override {
    return gate_.check(who.role, unit, pdu, who.name);
  }

  MotionStops motion_stops(std::size_t bus) const override { return backend_.safety->motion_stops(bus); }
  std::optional<std::string> motion_refusal(std::size_t bus, std::uint8_t servo) const override {
    return backend_.safety->motion_refusal(bus, servo);
  }

  void login(std::string_view address, std::string user, std::string password,
             std::function<void(LoginOutcome)> done) override {
    logins_.login(address, std::move(user), std::move(password), std::move(done));
  }

  void jog_modbus(const Principal& who, std::uint8_t unit, Bytes pdu, const JogSession& session,
                  std::function<void(ModbusAnswer)> done) override {
    submit(who, unit, std::move(pdu), std::move(done), session);
  }

  // A request for the router as `who`; with `jog`, a write of that hold-to-run move (jog_modbus).
  void submit(const Principal& who, std::uint8_t unit, Bytes pdu, std::function<void(ModbusAnswer)> done,
              std::optional<JogSession> jog) {
    if (const auto refusal = this->refusal(who, unit, pdu)) {
      ModbusAnswer answer;
      answer.exception = static_cast<std::uint8_t>(refusal->exception);
      answer.pdu = refusal->answer(pdu);
      answer.message = refusal->text();
      answer.role_refused = true;
      return done(std::move(answer));
    }
    auto target = std::make_shared<ConsoleReply>(mailbox_, std::move(done));
    auto origin = std::make_shared<const std::string>("the browser console (" + who.name + ")");
    backend_.post_to_router([router = backend_.router, safety = backend_.safety, unit, pdu = std::move(pdu), target,
                             origin, jog = std::move(jog)] {
      const Reply reply(target, 0, origin);
      // The e-stop is latched and reset, and watchdogs re-armed, on this thread, and the router
      // admits the write on it right after this look: no latch and reset can come between them.
      if (jog && jog->ended(safety->motion_stops(jog->bus()))) {
        return reply.send(  // 0x04: motion blocked, as the router answers it
            exception_response(pdu.empty() ? 0 : pdu[0], ModbusException::ServerDeviceFailure));
      }
      router->handle(unit, pdu, reply);
    });
  }

  // --- for sessions (console thread) -----------------------------------------------------------
  const ConsoleLimits& limits() const { return limits_; }
  ssl::context* ssl_context() { return ssl_.get(); }
  void add(Connection* connection) { connections_.insert(connection); }
  void remove(Connection* connection) { connections_.erase(connection); }
  void add_socket(Socket* socket) { sockets_.insert(socket); }
  Door& door() { return door_; }
  DoorStats door_stats() const { return door_.stats(); }
  void remove_socket(Socket* socket) { sockets_.erase(socket); }

  // The principal of a request, its session, and a Set-Cookie for a session made now.
  struct Identity {
    Principal who;
    std::optional<Session> session;
    std::string set_cookie;
  };
  Identity identify(const http::request<http::string_body>& request, const Peer& peer) {
    Identity identity;
    if (const auto header = request.find(http::field::cookie); header != request.end()) {
      if (const auto token = cookie_value(view(header->value()), kCookieName))
        identity.session = sessions_.find(*token);
    }
    if (identity.session) {
      identity.who = identity.session->who;
      return identity;
    }
    identity.who = peer.certificate ? *peer.certificate : implicit_principal(rules_, peer.loopback);
    if (identity.who.role != config::Role::None) {
      identity.session = sessions_.create(identity.who);
      identity.set_cookie = session_cookie(identity.session->token);
    }
    return identity;
  }

  // A route for the request's method and path; the answer to give instead when there is none.
  struct Match {
    const Route* route = nullptr;
    PathParams params;
    std::optional<HttpAnswer> refusal;
  };
  Match match(std::string_view method, std::string_view target) const {
    Match found;
    bool path_known = false;
    const std::string_view path = path_of(target);
    for (const auto& route : console_routes()) {
      PathParams params;
      if (!match_path(route.pattern, path, params)) continue;
      path_known = true;
      if (route.method != method) continue;
      found.route = &route;
      found.params = std::move(params);
      return found;
    }
    found.refusal = path_known
                        ? HttpAnswer::error(405, "method " + printable(method) + " is not used on " + printable(path))
                        : HttpAnswer::error(404, "no page " + printable(path) + " here; the overview is at /");
    return found;
  }

  // Whether `who` may use `route` (and with which answer not); also the CSRF rule for POSTs.
  std::optional<HttpAnswer> refusal(const Route& route, const Identity& identity,
                                    const http::request<http::string_body>& request, std::string_view path) const {
    if (!role_allows(identity.who.role, route.need)) {
      if (identity.who.role == config::Role::None) {
        if (route.kind == RouteKind::Page) {
          HttpAnswer answer{
              303, "text/plain; charset=utf-8", "log in first\n", {{"Location", "/login?next=" + std::string(path)}}};
          return answer;
        }
        return HttpAnswer::json(401, {{"error", "log in first"}, {"login", true}});
      }
      return HttpAnswer::error(403, std::string(route.pattern) + " needs the " +
                                        std::string(config::to_string(route.need)) + " role; " + identity.who.name +
                                        " has " + std::string(config::to_string(identity.who.role)) + "; nothing done");
    }
    if (route.method == "POST" && route.csrf) {
      const auto header = request.find("X-CSRF-Token");
      const std::string_view token = header == request.end() ? std::string_view() : view(header->value());
      if (!identity.session || !same_token(token, identity.session->csrf)) {
        return HttpAnswer::error(403, token.empty()
                                          ? "missing CSRF token (X-CSRF-Token); nothing done"
                                          : "stale CSRF token (a new login or a gateway restart replaced it): "
                                            "reload the page; nothing done");
      }
    }
    return std::nullopt;
  }

  HttpAnswer page(const Route& route, const PathParams& params) const {
    std::string_view name = route.page;
    if (name.empty()) name = params.get("file").value_or("");
    if (name == "chart.js") {
      if (chart_js_.empty()) {
        return HttpAnswer{
            503, "text/plain; charset=utf-8", "Chart.js is not installed: apt install libjs-chart.js\n", {}};
      }
      return HttpAnswer{200, "text/javascript; charset=utf-8", chart_js_, {{"Cache-Control", "max-age=3600"}}};
    }
    const WebAsset* asset = find_web_asset(name);
    if (asset == nullptr) return HttpAnswer::error(404, "no file " + printable(name) + " here");
    return HttpAnswer{
        200, std::string(asset->content_type), std::string(asset->bytes), {{"Cache-Control", "no-cache"}}};
  }

  // A request with a role makes its connection one the console serves (until then it may make
  // room for others, gateway/net/door.h); nullopt, or the answer when the served budget is full.
  std::optional<HttpAnswer> trust(const Identity& identity, Peer& peer) {
    if (identity.who.role == config::Role::None || door_.trust(peer.ticket)) return std::nullopt;
    peer.over_budget = true;
    return HttpAnswer::error(503, "the console serves " + std::to_string(limits_.door.max_served) +
                                      " signed-in connections already (its limit): close a tab or another browser "
                                      "and try again");
  }

  void handle_http(const http::request<http::string_body>& request, Peer& peer, std::function<void(HttpAnswer)> done) {
    const std::string_view target = view(request.target());
    Match found = match(view(request.method_string()), target);
    if (!found.route) return done(std::move(*found.refusal));
    const Route& route = *found.route;
    if (route.kind == RouteKind::Socket) return done(HttpAnswer::error(400, "this URL is a WebSocket; open it as one"));
    Identity identity = identify(request, peer);
    if (auto busy = trust(identity, peer)) return done(std::move(*busy));
    auto with_cookie = [cookie = identity.set_cookie, done = std::move(done)](HttpAnswer answer) {
      if (!cookie.empty()) answer.headers.emplace_back("Set-Cookie", cookie);
      done(std::move(answer));
    };
    if (auto refused = refusal(route, identity, request, path_of(target))) return with_cookie(std::move(*refused));
    if (route.kind == RouteKind::Page) {
      if (route.missing != nullptr) {
        if (auto missing = route.missing(*this, found.params)) return with_cookie(error_page(*missing));
      }
      return with_cookie(page(route, found.params));
    }
    auto call =
        std::make_shared<ApiCall>(ApiCall{*this, std::move(found.params), request.body(), identity.who,
                                          identity.session, peer.loopback, std::move(with_cookie), peer.address});
    try {
      route.api(call);
    } catch (const std::exception& error) {
      spdlog::error("console: {} {} failed: {}", view(request.method_string()), printable(target), error.what());
      call->answer(HttpAnswer::error(500, std::string("the console failed: ") + error.what()));
    }
  }

  // A WebSocket upgrade: the stream to run, or the answer refusing it.
  Expected<std::pair<std::unique_ptr<Stream>, std::string>, HttpAnswer> open_socket(
      const http::request<http::string_body>& request, Peer& peer) {
    const std::string_view target = view(request.target());
    Match found = match("GET", target);
    if (!found.route) return unexpected(std::move(*found.refusal));
    if (found.route->kind != RouteKind::Socket) return unexpected(HttpAnswer::error(400, "not a WebSocket URL"));
    Identity identity = identify(request, peer);
    if (auto busy = trust(identity, peer)) return unexpected(std::move(*busy));
    if (auto refused = refusal(*found.route, identity, request, path_of(target)))
      return unexpected(std::move(*refused));
    // Another site's page may open a WebSocket here with the user's cookie: the origin must be
    // this server and the URL must carry the session's CSRF token.
    if (const auto origin = request.find(http::field::origin); origin != request.end()) {
      const auto host = request.find(http::field::host);
      const std::string expected_http = "http://" + std::string(host == request.end() ? "" : view(host->value()));
      const std::string expected_https = "https://" + std::string(host == request.end() ? "" : view(host->value()));
      const std::string_view from = view(origin->value());
      if (from != expected_http && from != expected_https) {
        return unexpected(HttpAnswer::error(403, "WebSocket from another origin (" + printable(from) + ") refused"));
      }
    }
    const auto csrf = query_value(target, "csrf");
    if (!identity.session || !csrf || !same_token(*csrf, identity.session->csrf)) {
      return unexpected(HttpAnswer::error(403, "missing or stale CSRF token in the WebSocket URL: reload the page"));
    }
    auto stream = found.route->socket(*this, found.params, identity.who);
    if (!stream) return unexpected(HttpAnswer::error(404, stream.error()));
    return std::make_pair(std::move(*stream), identity.who.name);
  }

  std::optional<Principal> certificate_principal(SSL* ssl) const {
    if (!settings_.tls) return std::nullopt;  // the console's own certificate: no client certificates
    X509* certificate = SSL_get1_peer_certificate(ssl);
    if (certificate == nullptr) return std::nullopt;
    const PeerCertificate peer = read_certificate(certificate);
    X509_free(certificate);
    const RoleDecision decision = role_for(*backend_.config->modbus_tcp.tls, peer);
    if (decision.role == config::Role::None) return std::nullopt;
    return Principal{peer.subject, decision.role, "client certificate (" + decision.source + ")"};
  }

 private:
  std::string access_summary() const {
    if (rules_.local_every_right) return "simulated servos: the local user has every right";
    std::string text;
    if (rules_.users) text = std::to_string(settings_.users.size()) + " user(s) with passwords";
    if (rules_.certificates) text += std::string(text.empty() ? "" : ", ") + "client certificates";
    return text.empty() ? "read-only: no users and no tls configured" : text;
  }

  void accept();
  void schedule_tick() {
    timer_.expires_after(kSamplePeriod);
    timer_.async_wait([this](const beast::error_code& error) {
      if (error) return;
      const auto now = SteadyClock::now();
      const bool push = now - last_push_ >= kPushPeriod - kSamplePeriod / 2;
      if (push) last_push_ = now;
      const auto sockets = sockets_;
      for (auto* socket : sockets) {
        if (sockets_.contains(socket)) socket->tick(now, push);
      }
      schedule_tick();
    });
  }
  void close_all() {
    beast::error_code ignored;
    acceptor_.close(ignored);
    timer_.cancel();
    door_.close();
    const auto connections = connections_;
    for (auto* connection : connections) {
      if (connections_.contains(connection)) connection->close();
    }
  }

  const config::ConsoleConfig settings_;
  const ConsoleBackend backend_;
  const ConsoleLimits limits_;
  const AccessRules rules_;
  AccessGate gate_;  // console thread: every request's role, before the router
  SessionStore sessions_;
  Commissioning commissioning_;
  std::shared_ptr<ssl::context> ssl_;
  std::string chart_js_;
  nlohmann::json overview_;
  SteadyClock::time_point overview_at_{};
  SteadyClock::time_point last_push_{};
  std::uint16_t port_ = 0;
  std::set<Connection*> connections_;  // before io_: handlers destroyed with io_ still unregister
  std::set<Socket*> sockets_;
  asio::io_context io_;
  tcp::acceptor acceptor_;
  asio::steady_timer timer_;
  std::shared_ptr<Mailbox> mailbox_;
  LoginGuard logins_;  // its worker posts answers through mailbox_
  // After io_: destroyed first, once stop() has closed every connection (connections leave the
  // door when they close, never in a destructor, which may run when io_ is destroyed).
  Door door_;
  std::thread thread_;
};

namespace {

using Impl = ConsoleServer::Impl;

template <typename Stream>
tcp::socket& socket_of(Stream& stream) {
  return beast::get_lowest_layer(stream).socket();
}

// One WebSocket: the route's stream stepped by the server's timer, a page's messages handed to it.
template <typename Transport>
class WebSocketSession final : public Socket, public std::enable_shared_from_this<WebSocketSession<Transport>> {
 public:
  // `ticket`: the connection's at the door, handed over by the HttpSession it came from.
  WebSocketSession(Transport transport, Impl& server, std::unique_ptr<Stream> stream, std::string who,
                   Door::Ticket ticket)
      : ws_(std::move(transport)), server_(server), stream_(std::move(stream)), who_(std::move(who)), ticket_(ticket) {
    server_.add(this);
  }
  ~WebSocketSession() override {
    server_.remove(this);
    server_.remove_socket(this);
  }

  void accept(http::request<http::string_body> request) {
    ws_.read_message_max(server_.limits().max_message_bytes);
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    ws_.set_option(websocket::stream_base::decorator(
        [](websocket::response_type& response) { response.set(http::field::server, view(kServerName)); }));
    beast::get_lowest_layer(ws_).expires_never();
    ws_.async_accept(request, [self = this->shared_from_this()](const beast::error_code& error) {
      if (error) return self->finish();
      self->server_.add_socket(self.get());
      self->read();
    });
  }

  void tick(SteadyClock::time_point now, bool push) override {
    if (finished_) return;
    stream_->sample(now);
    if (!push) return;
    if (auto message = stream_->flush(now)) send(std::move(*message));
  }

  void close() override {
    finish();
    beast::error_code ignored;
    socket_of(ws_.next_layer()).shutdown(tcp::socket::shutdown_both, ignored);
    socket_of(ws_.next_layer()).close(ignored);
  }

 private:
  void read() {
    ws_.async_read(buffer_, [self = this->shared_from_this()](const beast::error_code& error, std::size_t) {
      if (error) {
        if (error != websocket::error::closed && error != asio::error::operation_aborted) {
          spdlog::debug("console: WebSocket of {} ended: {}", self->who_, error.message());
        }
        return self->finish();
      }
      const std::string text = beast::buffers_to_string(self->buffer_.data());
      self->buffer_.consume(self->buffer_.size());
      if (!self->finished_) {
        std::weak_ptr<WebSocketSession> weak = self;
        self->stream_->on_message(text, [weak](std::string message) {
          if (auto session = weak.lock()) session->send(std::move(message));
        });
      }
      self->read();
    });
  }

  void send(std::string message) {
    if (finished_) return;
    if (queue_.size() >= kMaxQueuedMessages) {
      spdlog::info("console: closing the WebSocket of {}: it reads slower than the gateway pushes", who_);
      return close();
    }
    queue_.push_back(std::move(message));
    if (queue_.size() == 1) write();
  }

  void write() {
    ws_.text(true);
    ws_.async_write(asio::buffer(queue_.front()),
                    [self = this->shared_from_this()](const beast::error_code& error, std::size_t) {
                      if (error) return self->finish();
                      self->queue_.pop_front();
                      if (!self->queue_.empty()) self->write();
                    });
  }

  // The page is gone (or the server stops): the stream hears it once (a hold-to-run move stops).
  void finish() {
    if (finished_) return;
    finished_ = true;
    server_.door().leave(ticket_);
    server_.remove_socket(this);
    stream_->on_close();
  }

  websocket::stream<Transport> ws_;
  Impl& server_;
  std::unique_ptr<Stream> stream_;
  std::string who_;
  beast::flat_buffer buffer_;
  std::deque<std::string> queue_;
  Door::Ticket ticket_;
  bool finished_ = false;
};

// One HTTP connection: requests answered one at a time; a WebSocket upgrade hands the
// connection over to a WebSocketSession.
template <typename Transport>
class HttpSession final : public Connection,
                          public DoorGuest,
                          public std::enable_shared_from_this<HttpSession<Transport>> {
 public:
  HttpSession(Transport transport, Impl& server, Peer peer)
      : transport_(std::move(transport)), server_(server), peer_(std::move(peer)) {
    beast::error_code error;
    const auto endpoint = socket_of(transport_).remote_endpoint(error);
    peer_text_ = error ? peer_.address : peer_.address + ":" + std::to_string(endpoint.port());
    server_.add(this);
  }
  ~HttpSession() override { server_.remove(this); }

  // Through the door first (false: refused, closed); then, once the client's first bytes are
  // there, the TLS handshake or the first read: until then the connection is silent() without
  // doubt (nothing sits unseen in a TLS or HTTP parser's buffer).
  bool start() {
    const auto ticket = server_.door().admit(peer_.address, this->weak_from_this());
    if (!ticket) {
      close();
      return false;
    }
    peer_.ticket = *ticket;
    socket_of(transport_)
        .async_wait(tcp::socket::wait_read, [self = this->shared_from_this()](const beast::error_code& error) {
          if (self->closed_) return;
          self->spoke_ = true;
          if (error) return self->close();
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

 private:
  void begin() {
    if constexpr (std::is_same_v<Transport, beast::ssl_stream<beast::tcp_stream>>) {
      beast::get_lowest_layer(transport_).expires_after(server_.limits().request_timeout);
      transport_.async_handshake(
          ssl::stream_base::server, [self = this->shared_from_this()](const beast::error_code& error) {
            if (error) {
              spdlog::debug("console: TLS handshake with {} failed: {}", self->peer_.address, error.message());
              return self->close();
            }
            self->peer_.certificate = self->server_.certificate_principal(self->transport_.native_handle());
            self->read();
          });
    } else {
      read();
    }
  }

 public:
  void close() override {
    if (closed_) return;
    closed_ = true;
    if (!handed_over_) server_.door().leave(peer_.ticket);
    beast::error_code ignored;
    socket_of(transport_).shutdown(tcp::socket::shutdown_both, ignored);
    socket_of(transport_).close(ignored);
  }

 private:
  void read() {
    parser_.emplace();
    parser_->header_limit(static_cast<std::uint32_t>(server_.limits().max_header_bytes));
    parser_->body_limit(server_.limits().max_body_bytes);
    beast::get_lowest_layer(transport_).expires_after(server_.limits().request_timeout);
    http::async_read(
        transport_, buffer_, *parser_,
        [self = this->shared_from_this()](const beast::error_code& error, std::size_t) { self->on_read(error); });
  }

  void on_read(const beast::error_code& error) {
    if (error) {
      if (auto answer = answer_for_read_error(error)) return write(std::move(*answer), false, 11);
      return close();
    }
    server_.door().heard(peer_.ticket);
    auto request = parser_->release();
    if (websocket::is_upgrade(request)) {
      auto opened = server_.open_socket(request, peer_);
      if (!opened) return write(opened.error(), false, request.version());
      handed_over_ = true;
      closed_ = true;  // this object's part is over: the socket and the ticket are the WebSocket's
      auto session = std::make_shared<WebSocketSession<Transport>>(
          std::move(transport_), server_, std::move(opened->first), std::move(opened->second), peer_.ticket);
      session->accept(std::move(request));
      return;  // this connection now belongs to the WebSocket session
    }
    const bool keep_alive = request.keep_alive();
    const unsigned version = request.version();
    const bool head = request.method() == http::verb::head;
    if (head) request.method(http::verb::get);
    server_.handle_http(request, peer_,
                        [self = this->shared_from_this(), keep_alive, version, head](HttpAnswer answer) {
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
    beast::get_lowest_layer(transport_).expires_after(server_.limits().request_timeout);
    http::async_write(transport_, *response_,
                      [self = this->shared_from_this(), keep_alive](const beast::error_code& error, std::size_t) {
                        self->response_.reset();
                        if (error || !keep_alive) return self->close();
                        self->read();
                      });
  }

  Transport transport_;
  Impl& server_;
  Peer peer_;
  std::string peer_text_;
  bool spoke_ = false;  // the client's first bytes came (or its connection failed)
  bool closed_ = false;
  bool handed_over_ = false;  // to a WebSocketSession, with the door's ticket
  beast::flat_buffer buffer_;
  std::optional<http::request_parser<http::string_body>> parser_;
  std::optional<http::response<http::string_body>> response_;
};

}  // namespace

void ConsoleServer::Impl::accept() {
  acceptor_.async_accept([this](const beast::error_code& error, tcp::socket socket) {
    if (!acceptor_.is_open()) return;
    if (error) {
      if (error == asio::error::operation_aborted) return;
      spdlog::warn("console: accepting a connection failed: {}", error.message());
      return accept();
    }
    beast::error_code ignored;
    const auto remote = socket.remote_endpoint(ignored);
    Peer peer{remote.address().is_loopback(), remote.address().to_string(), std::nullopt, 0, false};
    if (ssl_) {
      std::make_shared<HttpSession<beast::ssl_stream<beast::tcp_stream>>>(
          beast::ssl_stream<beast::tcp_stream>(beast::tcp_stream(std::move(socket)), *ssl_), *this, std::move(peer))
          ->start();
    } else {
      std::make_shared<HttpSession<beast::tcp_stream>>(beast::tcp_stream(std::move(socket)), *this, std::move(peer))
          ->start();
    }
    accept();
  });
}

ConsoleServer::ConsoleServer(config::ConsoleConfig settings, ConsoleBackend backend, ConsoleLimits limits)
    : impl_(std::make_unique<Impl>(std::move(settings), std::move(backend), limits)) {}
ConsoleServer::~ConsoleServer() = default;
void ConsoleServer::start() { impl_->start(); }
void ConsoleServer::stop() { impl_->stop(); }
std::uint16_t ConsoleServer::port() const { return impl_->port(); }
LoginStats ConsoleServer::login_stats() const { return impl_->login_stats(); }
std::string ConsoleServer::url() const { return impl_->url(); }
DoorStats ConsoleServer::door_stats() const { return impl_->door_stats(); }

}  // namespace sms::gateway::console
