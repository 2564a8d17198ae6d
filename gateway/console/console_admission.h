#pragma once
// Who a console request is and whether it may do what it asks (docs/CONSOLE.md "Access"): the
// route its method and path name, the principal behind it (session cookie, client certificate,
// the loopback user), the route's role, the CSRF token of a state-changing request, and a
// WebSocket's origin. The connections (console_http.cpp) only carry the bytes; the services
// (console_server.cpp) only run what was admitted.
#include <openssl/ssl.h>

#include <optional>
#include <string>
#include <string_view>

#include "config/config.h"
#include "gateway/console/console_access.h"
#include "gateway/console/console_request.h"
#include "gateway/console/console_routes.h"

namespace sms::gateway::console {

inline constexpr std::string_view kSessionCookieName = "sms_console";

// The route for a request's method and target; the answer to give instead when there is none
// (404 for an unknown path, 405 for a known path with another method).
struct RouteMatch {
  const Route* route = nullptr;
  PathParams params;
  std::optional<HttpAnswer> refusal;
};
RouteMatch match_route(std::string_view method, std::string_view target);

// The principal of a request, its session, and a Set-Cookie for a session made now.
struct Identity {
  Principal who;
  std::optional<Session> session;
  std::string set_cookie;
};

// What a request carries that admission reads (the HTTP layer's values, without Beast).
struct RequestFacts {
  std::string_view target;
  std::optional<std::string_view> cookie;  // the Cookie header
  std::optional<std::string_view> csrf;    // the X-CSRF-Token header
  std::optional<std::string_view> origin;  // the Origin header (a WebSocket upgrade)
  std::string_view host;                   // the Host header
  bool peer_loopback = false;
  const std::optional<Principal>* certificate = nullptr;  // HTTPS with a client certificate that has a role
};

class Admission {
 public:
  // All must outlive it; `settings` are the console's (console.*, or --console's).
  Admission(const config::Config& config, const config::ConsoleConfig& settings, SessionStore& sessions);

  // The session of the request's cookie; else its certificate's or the loopback user's
  // principal, with a new session (and its cookie) when that principal has a role.
  Identity identify(const RequestFacts& request);
  // Whether `identity` may use `route`, and the CSRF rule for a POST; nullopt: admitted.
  std::optional<HttpAnswer> refusal(const Route& route, const Identity& identity, const RequestFacts& request) const;
  // A WebSocket upgrade also needs this server's origin and the session's token in its URL:
  // another site's page could otherwise open one with the user's cookie.
  std::optional<HttpAnswer> socket_refusal(const Identity& identity, const RequestFacts& request) const;
  // The principal a TLS client certificate gives (console.tls only); nullopt: none or no role.
  std::optional<Principal> certificate_principal(SSL* ssl) const;

  // The session cookie for `token` (empty: one that clears the cookie).
  std::string session_cookie(const std::string& token) const;
  // "2 user(s) with passwords, client certificates" for the start-up log line.
  std::string summary() const;
  const AccessRules& rules() const { return rules_; }

 private:
  const config::Config& config_;
  const config::ConsoleConfig& settings_;
  const AccessRules rules_;
  SessionStore& sessions_;
};

}  // namespace sms::gateway::console
