#include "gateway/console/console_admission.h"

#include "gateway/modbus_tcp/tls.h"

namespace sms::gateway::console {

RouteMatch match_route(std::string_view method, std::string_view target) {
  RouteMatch found;
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

Admission::Admission(const config::Config& config, const config::ConsoleConfig& settings, SessionStore& sessions)
    : config_(config), settings_(settings), rules_(access_rules(settings_)), sessions_(sessions) {}

Identity Admission::identify(const RequestFacts& request) {
  Identity identity;
  if (request.cookie) {
    if (const auto token = cookie_value(*request.cookie, kSessionCookieName)) identity.session = sessions_.find(*token);
  }
  if (identity.session) {
    identity.who = identity.session->who;
    return identity;
  }
  const bool certified = request.certificate != nullptr && request.certificate->has_value();
  identity.who = certified ? **request.certificate : implicit_principal(rules_, request.peer_loopback);
  if (identity.who.role != config::Role::None) {
    identity.session = sessions_.create(identity.who);
    identity.set_cookie = session_cookie(identity.session->token);
  }
  return identity;
}

std::optional<HttpAnswer> Admission::refusal(const Route& route, const Identity& identity,
                                             const RequestFacts& request) const {
  if (!role_allows(identity.who.role, route.need)) {
    if (identity.who.role == config::Role::None) {
      if (route.kind == RouteKind::Page) {
        return HttpAnswer{303,
                          "text/plain; charset=utf-8",
                          "log in first\n",
                          // The whole target, its query too (a servo page's ?unit=), encoded as one value.
                          {{"Location", "/login?next=" + percent_encode(request.target)}}};
      }
      return HttpAnswer::json(401, {{"error", "log in first"}, {"login", true}});
    }
    return HttpAnswer::error(403, std::string(route.pattern) + " needs the " +
                                      std::string(config::to_string(route.need)) + " role; " + identity.who.name +
                                      " has " + std::string(config::to_string(identity.who.role)) + "; nothing done");
  }
  if (route.method == "POST" && route.csrf) {
    const std::string_view token = request.csrf.value_or(std::string_view());
    if (!identity.session || !same_token(token, identity.session->csrf)) {
      return HttpAnswer::error(403, token.empty() ? "missing CSRF token (X-CSRF-Token); nothing done"
                                                  : "stale CSRF token (a new login or a gateway restart replaced it): "
                                                    "reload the page; nothing done");
    }
  }
  return std::nullopt;
}

std::optional<HttpAnswer> Admission::socket_refusal(const Identity& identity, const RequestFacts& request) const {
  if (request.origin) {
    // The page's own origin: this console's scheme and the host it was asked by; an https:// page
    // may not open the plain HTTP console's socket, nor the reverse.
    const std::string own = std::string(settings_.https() ? "https://" : "http://") + std::string(request.host);
    if (*request.origin != own) {
      return HttpAnswer::error(403, "WebSocket from another origin (" + printable(*request.origin) + ") refused");
    }
  }
  const auto csrf = query_value(request.target, "csrf");
  if (!identity.session || !csrf || !same_token(*csrf, identity.session->csrf)) {
    return HttpAnswer::error(403, "missing or stale CSRF token in the WebSocket URL: reload the page");
  }
  return std::nullopt;
}

std::optional<Principal> Admission::certificate_principal(SSL* ssl) const {
  if (!settings_.tls) return std::nullopt;  // the console's own certificate: no client certificates
  X509* certificate = SSL_get1_peer_certificate(ssl);
  if (certificate == nullptr) return std::nullopt;
  const PeerCertificate peer = read_certificate(certificate);
  X509_free(certificate);
  const RoleDecision decision = role_for(*config_.modbus_tcp.tls, peer);
  if (decision.role == config::Role::None) return std::nullopt;
  return Principal{peer.subject, decision.role, "client certificate (" + decision.source + ")"};
}

std::string Admission::session_cookie(const std::string& token) const {
  std::string cookie = std::string(kSessionCookieName) + "=" + token + "; Path=/; HttpOnly; SameSite=Strict";
  if (settings_.https()) cookie += "; Secure";
  if (token.empty()) cookie += "; Max-Age=0";
  return cookie;
}

std::string Admission::summary() const {
  if (rules_.local_every_right) return "simulated servos: the local user has every right";
  std::string text;
  if (rules_.users) text = std::to_string(settings_.users.size()) + " user(s) with passwords";
  if (rules_.certificates) text += std::string(text.empty() ? "" : ", ") + "client certificates";
  return text.empty() ? "read-only: no users and no tls configured" : text;
}

}  // namespace sms::gateway::console
