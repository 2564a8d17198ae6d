// The console's server: its listener, thread and timer, the services its routes use, and the
// dispatch of a request to its route once admitted (console_admission.h). The connections are
// console_http.cpp and console_websocket.cpp.
#include "gateway/console/console_server.h"

#include <fstream>
#include <mutex>
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

#include "gateway/console/console_admission.h"
#include "gateway/console/console_commission.h"
#include "gateway/console/console_connection.h"
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
namespace ssl = asio::ssl;
using tcp = asio::ip::tcp;

namespace {

// 127.0.0.0/8 and ::1, and an IPv4 loopback address as an IPv6 socket shows it (::ffff:127.0.0.1).
bool is_loopback(const asio::ip::address& address) {
  if (address.is_v6() && address.to_v6().is_v4_mapped()) {
    return asio::ip::make_address_v4(asio::ip::v4_mapped, address.to_v6()).is_loopback();
  }
  return address.is_loopback();
}

std::string_view view(beast::string_view text) { return {text.data(), text.size()}; }

// A header's value, nullopt when the request has none.
template <typename Field>
std::optional<std::string_view> header(const HttpRequest& request, Field field) {
  const auto found = request.find(field);
  if (found == request.end()) return std::nullopt;
  return view(found->value());
}

RequestFacts facts_of(const HttpRequest& request, const Peer& peer) {
  return RequestFacts{.target = view(request.target()),
                      .cookie = header(request, http::field::cookie),
                      .csrf = header(request, "X-CSRF-Token"),
                      .origin = header(request, http::field::origin),
                      .host = header(request, http::field::host).value_or(""),
                      .peer_loopback = peer.loopback,
                      .certificate = &peer.certificate};
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

DoorSettings door_settings(const ConsoleLimits& limits) {
  return {"console", "console", "complete HTTP request", limits.door, fixed_limit_names("the console"), nullptr};
}

}  // namespace

class ConsoleServer::Impl final : public Services, public ConnectionHost {
 public:
  Impl(config::ConsoleConfig settings, ConsoleBackend backend, ConsoleLimits limits)
      : settings_(std::move(settings)),
        backend_(std::move(backend)),
        limits_(limits),
        gate_(backend_.policy != nullptr ? *backend_.policy : throw std::invalid_argument("console: no role policy"),
              "console"),
        sessions_(settings_.session_timeout),
        admission_(*backend_.config, settings_, sessions_),
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
      if (admission_.rules().users) ssl_->set_verify_mode(ssl::verify_peer);
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
    spdlog::info("console: serving the browser console on {} ({}; {})", url(), admission_.summary(), door_.describe());
    if (settings_.insecure_http && admission_.rules().users && !config::is_loopback_host(settings_.listen.host)) {
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
  DoorStats door_stats() const { return door_.stats(); }
  std::string url() const {
    return std::string(settings_.https() ? "https" : "http") + "://" +
           config::HostPort{settings_.listen.host, port_}.to_string() + "/";
  }

  // --- Services: what routes use ---------------------------------------------------------------
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

  std::string session_cookie(const std::string& token) const override { return admission_.session_cookie(token); }

  void modbus(const Principal& who, std::uint8_t unit, Bytes pdu, std::function<void(ModbusAnswer)> done) override {
    submit(who, unit, std::move(pdu), std::move(done), std::nullopt);
  }

  std::optional<GateRefusal> refusal(const Principal& who, std::uint8_t unit,
                                     std::span<const std::uint8_t> pdu) override {
    return gate_.check(who.role, unit, pdu, who.name);
  }

  MotionStops motion_stops(std::size_t bus) const override { return backend_.safety->motion_stops(bus); }

  void hold_servo(const Principal& who, const ServoUnit& unit, std::function<void(bool)> done) override {
    backend_.safety->hold_servo(
        unit.bus_index, unit.servo_id, "the browser console (" + who.name + ")",
        [mailbox = mailbox_, done = std::move(done)](bool ok) { mailbox->post([done, ok] { done(ok); }); });
  }

  void login(std::string_view address, std::string user, std::string password,
             std::function<void(LoginOutcome)> done) override {
    logins_.login(address, std::move(user), std::move(password), std::move(done));
  }

  void jog_modbus(const Principal& who, std::uint8_t unit, Bytes pdu, const JogSession& session,
                  std::function<void(ModbusAnswer)> done) override {
    submit(who, unit, std::move(pdu), std::move(done), session);
  }

  // --- ConnectionHost: what connections use ----------------------------------------------------
  const ConsoleLimits& limits() const override { return limits_; }
  Door& door() override { return door_; }
  void add(Connection* connection) override { connections_.insert(connection); }
  void remove(Connection* connection) override { connections_.erase(connection); }
  void add_socket(Socket* socket) override { sockets_.insert(socket); }
  void remove_socket(Socket* socket) override { sockets_.erase(socket); }
  std::optional<Principal> certificate_principal(SSL* ssl) const override {
    return admission_.certificate_principal(ssl);
  }

  void handle_http(const HttpRequest& request, Peer& peer, std::function<void(HttpAnswer)> done) override {
    const RequestFacts facts = facts_of(request, peer);
    RouteMatch found = match_route(view(request.method_string()), facts.target);
    if (!found.route) return done(std::move(*found.refusal));
    const Route& route = *found.route;
    if (route.kind == RouteKind::Socket) return done(HttpAnswer::error(400, "this URL is a WebSocket; open it as one"));
    Identity identity = admission_.identify(facts);
    if (auto busy = trust(identity, peer)) return done(std::move(*busy));
    auto with_cookie = [cookie = identity.set_cookie, done = std::move(done)](HttpAnswer answer) {
      if (!cookie.empty()) answer.headers.emplace_back("Set-Cookie", cookie);
      done(std::move(answer));
    };
    if (auto refused = admission_.refusal(route, identity, facts)) return with_cookie(std::move(*refused));
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
      spdlog::error("console: {} {} failed: {}", view(request.method_string()), printable(facts.target), error.what());
      call->answer(HttpAnswer::error(500, std::string("the console failed: ") + error.what()));
    }
  }

  Expected<OpenedSocket, HttpAnswer> open_socket(const HttpRequest& request, Peer& peer) override {
    const RequestFacts facts = facts_of(request, peer);
    RouteMatch found = match_route("GET", facts.target);
    if (!found.route) return unexpected(std::move(*found.refusal));
    if (found.route->kind != RouteKind::Socket) return unexpected(HttpAnswer::error(400, "not a WebSocket URL"));
    Identity identity = admission_.identify(facts);
    if (auto busy = trust(identity, peer)) return unexpected(std::move(*busy));
    if (auto refused = admission_.refusal(*found.route, identity, facts)) return unexpected(std::move(*refused));
    if (auto refused = admission_.socket_refusal(identity, facts)) return unexpected(std::move(*refused));
    auto stream = found.route->socket(*this, found.params, identity.who);
    if (!stream) return unexpected(HttpAnswer::error(404, stream.error()));
    return OpenedSocket{std::move(*stream), identity.who.name};
  }

 private:
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

  // A request with a role makes its connection one the console serves (until then it may make
  // room for others, gateway/net/door.h); nullopt, or the answer when the served budget is full.
  std::optional<HttpAnswer> trust(const Identity& identity, Peer& peer) {
    if (identity.who.role == config::Role::None || door_.trust(peer.ticket)) return std::nullopt;
    peer.over_budget = true;
    return HttpAnswer::error(503, "the console serves " + std::to_string(limits_.door.max_served) +
                                      " signed-in connections already (its limit): close a tab or another browser "
                                      "and try again");
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

  void accept() {
    acceptor_.async_accept([this](const beast::error_code& error, tcp::socket socket) {
      if (!acceptor_.is_open()) return;
      if (error) {
        if (error == asio::error::operation_aborted) return;
        spdlog::warn("console: accepting a connection failed: {}", error.message());
        return accept();
      }
      beast::error_code ignored;
      const auto remote = socket.remote_endpoint(ignored);
      serve_connection(std::move(socket), ssl_.get(), *this,
                       Peer{is_loopback(remote.address()), remote.address().to_string(), std::nullopt, 0, false});
      accept();
    });
  }

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
  AccessGate gate_;  // console thread: every request's role, before the router
  SessionStore sessions_;
  Admission admission_;
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
