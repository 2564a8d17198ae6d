#pragma once
// Who may do what in the browser console (docs/CONSOLE.md "Access"). The rights are the roles of
// Modbus/TCP Security (README "Modbus/TCP Security"): read < operate < engineer, and a console
// write passes the same RolePolicy as a Modbus request before it reaches the unit router.
//
// A visitor becomes a Principal in one of four ways, tried in this order:
//   - a client certificate over HTTPS (console.tls), its role as Modbus/TCP Security gives it;
//   - a user who logged in with a password (console.users, libsodium crypto_pwhash_str hashes);
//   - with neither users nor tls configured: anyone on the loopback address, read-only
//     (`--simulate`: every right, the demo's local user);
//   - nobody: only the login page and static files.
// Every principal gets a session (cookie: HttpOnly, SameSite=Strict) with its own CSRF token,
// which every state-changing request must carry (header X-CSRF-Token, or `csrf` in a WebSocket
// URL): the browser sends cookies and client certificates by itself, the token it does not.
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>

#include "config/config.h"

namespace sms::gateway::console {

using SteadyClock = std::chrono::steady_clock;

// Whether `have` includes the rights of `need` (read < operate < engineer).
bool role_allows(config::Role have, config::Role need);

// libsodium crypto_pwhash_str (Argon2id, interactive limits): the text for console.users[].password_hash.
// Throws std::runtime_error when libsodium cannot (out of memory).
std::string hash_password(std::string_view password);
// crypto_pwhash_str_verify; false for a wrong password and for a malformed hash.
bool verify_password(const std::string& hash, std::string_view password);
// 32 random bytes as 64 hex digits (randombytes_buf): session and CSRF tokens.
std::string random_token();
// Constant-time comparison of two tokens (sodium_memcmp); false when the sizes differ.
bool same_token(std::string_view a, std::string_view b);

struct Principal {
  std::string name;  // "alice", "CN=hmi-3", "local user", "anonymous"
  config::Role role = config::Role::None;
  std::string how;  // "password", "client certificate", "loopback", "simulate"
};

struct Session {
  std::string token;  // the cookie's value
  std::string csrf;   // the token state-changing requests carry
  Principal who;
  SteadyClock::time_point last_use;
};

// The console's sessions, bounded: past `max_sessions` the least recently used goes. Thread-safe.
class SessionStore {
 public:
  SessionStore(std::chrono::seconds timeout, std::size_t max_sessions = 256);
  Session create(Principal who, SteadyClock::time_point now = SteadyClock::now());
  // The session of cookie `token`, touched; nullopt when unknown or expired (then removed).
  std::optional<Session> find(std::string_view token, SteadyClock::time_point now = SteadyClock::now());
  void remove(std::string_view token);
  std::size_t size() const;

 private:
  const std::chrono::seconds timeout_;
  const std::size_t max_sessions_;
  mutable std::mutex mutex_;
  std::map<std::string, Session, std::less<>> sessions_;
};

// How a request without a session is seen, from the configuration alone.
struct AccessRules {
  bool users = false;              // console.users configured: log in with a password
  bool certificates = false;       // console.tls: client certificates give roles
  bool local_every_right = false;  // --simulate: the loopback user may do everything
};
AccessRules access_rules(const config::ConsoleConfig& console);
// The principal a visitor from `peer_loopback` is without a session and without a certificate:
// the loopback user (read-only, or every right under --simulate) where neither users nor
// certificates are configured; else nobody (role none: log in first).
Principal implicit_principal(const AccessRules& rules, bool peer_loopback);

// Checks a login against console.users; nullopt for an unknown user or a wrong password (the
// caller says the same for both).
std::optional<Principal> check_login(const config::ConsoleConfig& console, std::string_view name,
                                     std::string_view password);

}  // namespace sms::gateway::console
