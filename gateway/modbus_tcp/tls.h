#pragma once
// Modbus/TCP Security (docs/SECURITY.md): the TLS context of the secure listener
// (TLS 1.2/1.3, client certificate required and verified against the configured CA), the role
// a client certificate gets, and the role's gate (gateway/service/access_gate.h) put in front of
// the unit router for each secure connection. Internal to gateway/ (Asio and OpenSSL in the
// header are fine here).
//
//   TlsService tls(config.modbus_tcp.tls, policy, router);  // throws std::runtime_error: bad file
//   options.tls = &tls;                                      // TcpServer does the handshakes
//   tls.reload();                                            // SIGHUP: new handshakes use the new files
#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <boost/asio/ssl/context.hpp>

#include "config/config.h"
#include "gateway/modbus_tcp/tcp_server.h"
#include "gateway/modbus_tcp/tls_stats.h"
#include "gateway/net/door.h"
#include "gateway/service/access_gate.h"
#include "gateway/service/rate_limited_log.h"
#include "gateway/service/role_policy.h"

namespace sms::gateway {

// The OID of the Modbus.org "MB/TCP Security" role extension: an ASN.1 UTF8String holding the
// role name.
inline constexpr std::string_view kRoleExtensionOid = "1.3.6.1.4.1.50316.802.1";

// What the gateway reads from a client certificate.
struct PeerCertificate {
  std::string subject;                        // one line, "CN=plc-1,O=Plant"
  std::string common_name;                    // empty when the subject has none
  std::vector<std::string> alt_names;         // DNS names, e-mail addresses, URIs, IP addresses
  std::optional<std::string> role_extension;  // the role extension's text, when present
};
PeerCertificate read_certificate(X509* certificate);

struct RoleDecision {
  config::Role role = config::Role::None;
  std::string source;  // "role extension", "roles[plc-1] (CN)", "default_role", or why none
};
// The role extension when its text is read, operate or engineer (`none` refuses), or a
// role_names entry; otherwise (no extension, or a text of another scheme not in role_names) the
// first `roles` entry naming the CN or a subjectAltName, else default_role.
RoleDecision role_for(const config::TlsConfig& settings, const PeerCertificate& certificate);

// A server context: TLS 1.2 minimum, the certificate chain and key, client certificates
// required and verified against the CA file, no session resumption (a reloaded CA applies to
// every new connection). Throws std::runtime_error naming the file and what is wrong.
std::shared_ptr<boost::asio::ssl::context> make_tls_context(const config::TlsConfig& settings);

// OpenSSL's error queue as one line (emptied): for errors that say why a file or handshake failed.
// Shared by every TLS listener (Modbus/TCP Security, the console's own certificate).
std::string openssl_error_text();

class TlsService {
 public:
  // Loads the files (throws std::runtime_error when it cannot). `router` answers the requests
  // the role rights (`policy`) let through; both must outlive the service.
  TlsService(const config::TlsConfig& settings, const RolePolicy& policy, RequestHandler& router);

  const config::TlsConfig& settings() const { return settings_; }
  // The context for the next handshake (thread-safe).
  std::shared_ptr<boost::asio::ssl::context> context() const;
  // Loads the files again (any thread). On success new handshakes use them; on failure the old
  // context stays and the log says why. True on success.
  bool reload();

  // After a handshake that succeeded: the handler for the connection (a RoleGate over the
  // router), or nullptr after logging and counting why the client is refused (no role).
  std::unique_ptr<RequestHandler> admit(SSL* ssl, const std::string& peer);
  // A handshake that failed: one log line with the reason and the peer, counted.
  void handshake_failed(const boost::system::error_code& error, SSL* ssl, const std::string& peer);
  // Closed in the handshake by the listener's door (gateway/net/door.h: evicted to make room,
  // or no complete handshake in time; the door logs it): counted as a handshake result.
  void handshake_closed_by_door(DoorClose why);
  void connection_closed();

  TlsStats stats() const;

 private:
  void count(std::string_view result);
  std::string describe_context() const;

  const config::TlsConfig settings_;
  RequestHandler& router_;
  const RolePolicy& policy_;
  mutable std::mutex mutex_;
  std::shared_ptr<boost::asio::ssl::context> context_;
  std::string certificate_expiry_;  // "2034-05-01 12:00:00 GMT", for the log
  TlsStats stats_;                  // under mutex_
  // Refused handshakes, one log per outcome at most once a second (a flood of connections that
  // close in the handshake must not flood the log); io thread only.
  std::map<std::string, RateLimitedLog, std::less<>> refusal_logs_;
  RefusalCounter refusals_;  // requests the connections' role gates refused
};

}  // namespace sms::gateway
