#pragma once
// What the Modbus/TCP Security listener counts (gateway/modbus_tcp/tls.h), for /metrics. No Asio, no OpenSSL.
#include <array>
#include <cstddef>
#include <cstdint>
#include <string_view>

namespace sms::gateway {

// Outcomes of a TLS handshake on the secure listener, as sms_gateway_tls_handshakes_total{result}.
inline constexpr std::array<std::string_view, 12> kHandshakeResults{
    "ok",               // verified, with a role: the connection is served
    "expired",          // the client certificate (or one above it) has expired
    "not_yet_valid",    // ... is not valid yet
    "unknown_ca",       // the certificate does not chain to modbus_tcp.tls.ca
    "bad_certificate",  // any other verification failure (signature, purpose, ...)
    "no_certificate",   // the client sent none
    "no_role",          // verified, but neither the role extension, roles nor default_role give a role
    "not_tls",          // the bytes were not TLS (plain Modbus on the TLS port, a scanner)
    "protocol",         // TLS, but nothing in common: a version below 1.2, no shared cipher
    "timeout",          // no complete handshake within modbus_tcp.tls.handshake_timeout_ms
    "evicted",          // closed in the handshake to make room for a newer one (max_handshakes...)
    "failed",           // anything else (connection closed or reset during the handshake)
};

struct TlsStats {
  std::array<std::uint64_t, kHandshakeResults.size()> handshakes{};  // by kHandshakeResults index
  std::uint64_t reloads_ok = 0;
  std::uint64_t reloads_failed = 0;
  std::uint64_t requests_refused_read = 0;  // requests refused by the role rights, by role
  std::uint64_t requests_refused_operate = 0;
  std::size_t open_connections = 0;
};

}  // namespace sms::gateway
