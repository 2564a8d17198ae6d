#include "gateway/console/console_access.h"

#include <sodium.h>

#include <stdexcept>

namespace sms::gateway::console {

namespace {

void ensure_sodium() {
  // sodium_init() is idempotent and thread-safe; -1 means no usable random source.
  if (sodium_init() < 0) throw std::runtime_error("libsodium could not start (no random source)");
}

}  // namespace

bool role_allows(config::Role have, config::Role need) {
  return static_cast<std::uint8_t>(have) >= static_cast<std::uint8_t>(need);
}

std::string hash_password(std::string_view password) {
  ensure_sodium();
  char out[crypto_pwhash_STRBYTES];
  if (crypto_pwhash_str(out, password.data(), password.size(), crypto_pwhash_OPSLIMIT_INTERACTIVE,
                        crypto_pwhash_MEMLIMIT_INTERACTIVE) != 0) {
    throw std::runtime_error("crypto_pwhash_str failed (out of memory)");
  }
  return std::string(out);
}

bool verify_password(const std::string& hash, std::string_view password) {
  ensure_sodium();
  if (hash.size() >= crypto_pwhash_STRBYTES) return false;
  return crypto_pwhash_str_verify(hash.c_str(), password.data(), password.size()) == 0;
}

std::string random_token() {
  ensure_sodium();
  unsigned char bytes[32];
  randombytes_buf(bytes, sizeof bytes);
  char hex[sizeof bytes * 2 + 1];
  sodium_bin2hex(hex, sizeof hex, bytes, sizeof bytes);
  return std::string(hex, sizeof bytes * 2);
}

bool same_token(std::string_view a, std::string_view b) {
  return a.size() == b.size() && !a.empty() && sodium_memcmp(a.data(), b.data(), a.size()) == 0;
}

SessionStore::SessionStore(std::chrono::seconds timeout, std::size_t max_sessions)
    : timeout_(timeout), max_sessions_(max_sessions) {}

Session SessionStore::create(Principal who, SteadyClock::time_point now) {
  Session session{random_token(), random_token(), std::move(who), now};
  std::lock_guard lock(mutex_);
  while (sessions_.size() >= max_sessions_) {
    auto oldest = sessions_.begin();
    for (auto it = sessions_.begin(); it != sessions_.end(); ++it) {
      if (it->second.last_use < oldest->second.last_use) oldest = it;
    }
    sessions_.erase(oldest);
  }
  sessions_.emplace(session.token, session);
  return session;
}

std::optional<Session> SessionStore::find(std::string_view token, SteadyClock::time_point now) {
  std::lock_guard lock(mutex_);
  const auto it = sessions_.find(token);
  if (it == sessions_.end()) return std::nullopt;
  if (now - it->second.last_use > timeout_) {
    sessions_.erase(it);
    return std::nullopt;
  }
  it->second.last_use = now;
  return it->second;
}

void SessionStore::remove(std::string_view token) {
  std::lock_guard lock(mutex_);
  if (const auto it = sessions_.find(token); it != sessions_.end()) sessions_.erase(it);
}

std::size_t SessionStore::size() const {
  std::lock_guard lock(mutex_);
  return sessions_.size();
}

AccessRules access_rules(const config::ConsoleConfig& console) {
  return AccessRules{!console.users.empty(), console.tls, console.local_user_has_every_right};
}

Principal implicit_principal(const AccessRules& rules, bool peer_loopback) {
  if (!peer_loopback || rules.users || rules.certificates) return Principal{"nobody", config::Role::None, "none"};
  if (rules.local_every_right) return Principal{"local user", config::Role::Engineer, "simulate"};
  return Principal{"local user", config::Role::Read, "loopback"};
}

std::optional<Principal> check_login(const config::ConsoleConfig& console, std::string_view name,
                                     std::string_view password) {
  for (const auto& user : console.users) {
    if (user.name != name) continue;
    if (!verify_password(user.password_hash, password)) return std::nullopt;
    return Principal{user.name, user.role, "password"};
  }
  // Same work for an unknown name, so the answer time does not tell which names exist.
  static const std::string kDummy = hash_password("not a user");
  (void)verify_password(kDummy, password);
  return std::nullopt;
}

}  // namespace sms::gateway::console
