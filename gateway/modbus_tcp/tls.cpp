#include "gateway/modbus_tcp/tls.h"

#include <arpa/inet.h>
#include <openssl/asn1.h>
#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <stdexcept>

#include <spdlog/spdlog.h>
#include <boost/asio/error.hpp>
#include <boost/asio/ssl/error.hpp>

#include "gateway/service/modbus_request.h"

namespace sms::gateway {

std::string openssl_error_text() {
  std::string text;
  while (const unsigned long code = ERR_get_error()) {
    char buffer[256];
    ERR_error_string_n(code, buffer, sizeof buffer);
    if (!text.empty()) text += "; ";
    text += buffer;
  }
  return text.empty() ? "unknown OpenSSL error" : text;
}

namespace {

namespace ssl = boost::asio::ssl;
using config::Role;

std::string bio_text(BIO* bio) {
  char* data = nullptr;
  const long size = BIO_get_mem_data(bio, &data);
  return size > 0 ? std::string(data, static_cast<std::size_t>(size)) : std::string();
}

std::string time_text(const ASN1_TIME* time) {
  if (time == nullptr) return "?";
  BIO* bio = BIO_new(BIO_s_mem());
  ASN1_TIME_print(bio, time);
  std::string text = bio_text(bio);
  BIO_free(bio);
  return text;
}

std::string name_text(const X509_NAME* name) {
  if (name == nullptr) return {};
  BIO* bio = BIO_new(BIO_s_mem());
  X509_NAME_print_ex(bio, name, 0, XN_FLAG_RFC2253);
  std::string text = bio_text(bio);
  BIO_free(bio);
  return text;
}

std::string asn1_string_text(const ASN1_STRING* value) {
  if (value == nullptr) return {};
  unsigned char* utf8 = nullptr;
  const int size = ASN1_STRING_to_UTF8(&utf8, value);
  if (size < 0) return {};
  std::string text(reinterpret_cast<const char*>(utf8), static_cast<std::size_t>(size));
  OPENSSL_free(utf8);
  return text;
}

// A file the context is built from: readable, or an error naming the key and the reason.
void check_readable(std::string_view key, const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw std::runtime_error("modbus_tcp.tls." + std::string(key) + " " + path +
                             ": cannot open: " + std::strerror(errno));
  }
}

std::string_view result_of_verify_error(long code) {
  switch (code) {
    case X509_V_ERR_CERT_HAS_EXPIRED: return "expired";
    case X509_V_ERR_CERT_NOT_YET_VALID: return "not_yet_valid";
    case X509_V_ERR_UNABLE_TO_GET_ISSUER_CERT:
    case X509_V_ERR_UNABLE_TO_GET_ISSUER_CERT_LOCALLY:
    case X509_V_ERR_UNABLE_TO_VERIFY_LEAF_SIGNATURE:
    case X509_V_ERR_SELF_SIGNED_CERT_IN_CHAIN:
    case X509_V_ERR_DEPTH_ZERO_SELF_SIGNED_CERT: return "unknown_ca";
    default: return "bad_certificate";
  }
}

// What a failed handshake was, from OpenSSL's reason code.
std::string_view result_of_ssl_reason(int reason) {
  switch (reason) {
    case SSL_R_PEER_DID_NOT_RETURN_A_CERTIFICATE: return "no_certificate";
    case SSL_R_WRONG_VERSION_NUMBER:
    case SSL_R_HTTP_REQUEST:
    case SSL_R_HTTPS_PROXY_REQUEST:
    case SSL_R_PACKET_LENGTH_TOO_LONG:
    case SSL_R_RECORD_LENGTH_MISMATCH:
    case SSL_R_UNEXPECTED_MESSAGE:
    case SSL_R_UNEXPECTED_RECORD:
    case SSL_R_LENGTH_MISMATCH:
    case SSL_R_BAD_PACKET_LENGTH: return "not_tls";
    case SSL_R_UNSUPPORTED_PROTOCOL:
    case SSL_R_NO_SHARED_CIPHER:
    case SSL_R_VERSION_TOO_LOW:
    case SSL_R_NO_PROTOCOLS_AVAILABLE:
    case SSL_R_NO_SHARED_SIGNATURE_ALGORITHMS: return "protocol";
    default: return "failed";
  }
}

// The private key in a PEM file (no passphrase: the callback refuses to ask), or nullptr.
EVP_PKEY* read_private_key(const std::string& path) {
  BIO* file = BIO_new_file(path.c_str(), "r");
  if (file == nullptr) return nullptr;
  EVP_PKEY* key = PEM_read_bio_PrivateKey(
      file, nullptr, [](char*, int, int, void*) { return 0; }, nullptr);
  BIO_free(file);
  return key;
}

// The certificate verification refused first, described for the log line of the refusal: the
// peer's certificate is not kept by OpenSSL when its verification fails.
void free_refused_text(void*, void* text, CRYPTO_EX_DATA*, int, long, void*) { delete static_cast<std::string*>(text); }

int refused_text_index() {
  static const int index = SSL_get_ex_new_index(0, nullptr, nullptr, nullptr, free_refused_text);
  return index;
}

// Whether every critical extension of `certificate` that OpenSSL does not handle itself is the
// role extension, which the gateway reads (read_certificate). Then "unhandled critical
// extension" is no reason to refuse it.
bool only_role_extension_unhandled(X509* certificate) {
  ASN1_OBJECT* role = OBJ_txt2obj(std::string(kRoleExtensionOid).c_str(), 1);
  if (role == nullptr) return false;
  bool handled = true;
  for (int i = 0; i < X509_get_ext_count(certificate) && handled; ++i) {
    X509_EXTENSION* extension = X509_get_ext(certificate, i);
    if (X509_EXTENSION_get_critical(extension) == 0 || X509_supported_extension(extension) != 0) continue;
    handled = OBJ_cmp(X509_EXTENSION_get_object(extension), role) == 0;
  }
  ASN1_OBJECT_free(role);
  return handled;
}

// The verify callback: accepts a critical role extension, and keeps the description of the
// first certificate refused.
int remember_refused_certificate(int ok, X509_STORE_CTX* store) {
  if (ok == 0 && X509_STORE_CTX_get_error(store) == X509_V_ERR_UNHANDLED_CRITICAL_EXTENSION) {
    X509* current = X509_STORE_CTX_get_current_cert(store);
    if (current != nullptr && only_role_extension_unhandled(current)) {
      X509_STORE_CTX_set_error(store, X509_V_OK);
      return 1;
    }
  }
  if (ok != 0) return ok;
  auto* ssl = static_cast<SSL*>(X509_STORE_CTX_get_ex_data(store, SSL_get_ex_data_X509_STORE_CTX_idx()));
  X509* certificate = X509_STORE_CTX_get_current_cert(store);
  if (ssl == nullptr || certificate == nullptr || SSL_get_ex_data(ssl, refused_text_index()) != nullptr) return ok;
  auto* text = new std::string("certificate " + name_text(X509_get_subject_name(certificate)) + ", issuer " +
                               name_text(X509_get_issuer_name(certificate)) + ", valid " +
                               time_text(X509_get0_notBefore(certificate)) + " to " +
                               time_text(X509_get0_notAfter(certificate)));
  if (SSL_set_ex_data(ssl, refused_text_index(), text) != 1) delete text;
  return ok;
}

std::size_t result_index(std::string_view result) {
  const auto found = std::find(kHandshakeResults.begin(), kHandshakeResults.end(), result);
  return static_cast<std::size_t>(found - kHandshakeResults.begin());
}

}  // namespace

PeerCertificate read_certificate(X509* certificate) {
  PeerCertificate peer;
  if (certificate == nullptr) return peer;
  const X509_NAME* subject = X509_get_subject_name(certificate);
  peer.subject = name_text(subject);
  const int cn = X509_NAME_get_index_by_NID(subject, NID_commonName, -1);
  if (cn >= 0) peer.common_name = asn1_string_text(X509_NAME_ENTRY_get_data(X509_NAME_get_entry(subject, cn)));

  if (auto* names =
          static_cast<GENERAL_NAMES*>(X509_get_ext_d2i(certificate, NID_subject_alt_name, nullptr, nullptr))) {
    for (int i = 0; i < sk_GENERAL_NAME_num(names); ++i) {
      const GENERAL_NAME* name = sk_GENERAL_NAME_value(names, i);
      switch (name->type) {
        case GEN_DNS:
        case GEN_EMAIL:
        case GEN_URI: peer.alt_names.push_back(asn1_string_text(name->d.ia5)); break;
        case GEN_IPADD: {
          const ASN1_OCTET_STRING* ip = name->d.iPAddress;
          char text[64] = {};
          if (ip->length == 4 || ip->length == 16) {
            const int family = ip->length == 4 ? AF_INET : AF_INET6;
            if (::inet_ntop(family, ip->data, text, sizeof text) != nullptr) peer.alt_names.emplace_back(text);
          }
          break;
        }
        default: break;
      }
    }
    GENERAL_NAMES_free(names);
  }

  ASN1_OBJECT* oid = OBJ_txt2obj(std::string(kRoleExtensionOid).c_str(), 1);
  const int at = oid != nullptr ? X509_get_ext_by_OBJ(certificate, oid, -1) : -1;
  ASN1_OBJECT_free(oid);
  if (at >= 0) {
    X509_EXTENSION* extension = X509_get_ext(certificate, at);
    const ASN1_OCTET_STRING* data = X509_EXTENSION_get_data(extension);
    const unsigned char* der = ASN1_STRING_get0_data(data);
    // The extension's value is a DER UTF8String; anything else is kept as "" (no valid role).
    ASN1_UTF8STRING* role = d2i_ASN1_UTF8STRING(nullptr, &der, ASN1_STRING_length(data));
    peer.role_extension = role != nullptr ? asn1_string_text(role) : std::string();
    ASN1_UTF8STRING_free(role);
  }
  return peer;
}

RoleDecision role_for(const config::TlsConfig& settings, const PeerCertificate& certificate) {
  // An extension text that is no role here (another scheme's "Operator") is not guessed at: it
  // is looked up in role_names, else the certificate is mapped as if it had no extension.
  std::string unmapped_extension;
  if (certificate.role_extension) {
    const std::string& text = *certificate.role_extension;
    if (const auto role = config::role_from_name(text)) {
      if (*role == Role::None) return {Role::None, "the role extension says `none`"};
      return {*role, "role extension"};
    }
    const auto named = std::find_if(settings.role_names.begin(), settings.role_names.end(),
                                    [&](const config::TlsRoleMapping& mapping) { return mapping.name == text; });
    if (named != settings.role_names.end()) {
      if (named->role == Role::None) return {Role::None, "role_names[" + text + "] is none"};
      return {named->role, "role extension `" + text + "` (role_names)"};
    }
    unmapped_extension = "role extension `" + text + "` not in role_names, so ";
  }
  for (const auto& mapping : settings.roles) {
    if (!certificate.common_name.empty() && mapping.name == certificate.common_name) {
      return {mapping.role, unmapped_extension + "roles[" + mapping.name + "] (CN)"};
    }
    if (std::find(certificate.alt_names.begin(), certificate.alt_names.end(), mapping.name) !=
        certificate.alt_names.end()) {
      return {mapping.role, unmapped_extension + "roles[" + mapping.name + "] (subjectAltName)"};
    }
  }
  if (settings.default_role != Role::None) return {settings.default_role, unmapped_extension + "default_role"};
  if (certificate.role_extension) {
    return {Role::None, "the role extension says `" + *certificate.role_extension +
                            "`, which is not read, operate, engineer nor in modbus_tcp.tls.role_names; no "
                            "modbus_tcp.tls.roles entry for its CN or subjectAltName, and no default_role"};
  }
  return {Role::None,
          "no role extension, no modbus_tcp.tls.roles entry for its CN or subjectAltName, and no "
          "default_role"};
}

std::shared_ptr<ssl::context> make_tls_context(const config::TlsConfig& settings) {
  check_readable("certificate", settings.certificate);
  check_readable("private_key", settings.private_key);
  check_readable("ca", settings.ca);
  auto context = std::make_shared<ssl::context>(ssl::context::tls_server);
  SSL_CTX* native = context->native_handle();
  ERR_clear_error();
  SSL_CTX_set_min_proto_version(native, TLS1_2_VERSION);
  SSL_CTX_set_options(native, SSL_OP_NO_RENEGOTIATION | SSL_OP_NO_TICKET | SSL_OP_CIPHER_SERVER_PREFERENCE);
  // No resumption: every connection presents its certificate to the CA loaded now.
  SSL_CTX_set_session_cache_mode(native, SSL_SESS_CACHE_OFF);
  SSL_CTX_set_num_tickets(native, 0);
  if (SSL_CTX_use_certificate_chain_file(native, settings.certificate.c_str()) != 1) {
    throw std::runtime_error("modbus_tcp.tls.certificate " + settings.certificate +
                             ": not a PEM certificate (chain): " + openssl_error_text());
  }
  // Read first and matched apart: SSL_CTX_use_PrivateKey_file also refuses a key of another
  // certificate, and its error would read as if the file were no key at all.
  EVP_PKEY* key = read_private_key(settings.private_key);
  if (key == nullptr) {
    throw std::runtime_error("modbus_tcp.tls.private_key " + settings.private_key +
                             ": not an unencrypted PEM private key: " + openssl_error_text());
  }
  const bool matches = X509_check_private_key(SSL_CTX_get0_certificate(native), key) == 1;
  ERR_clear_error();
  if (!matches) {
    EVP_PKEY_free(key);
    throw std::runtime_error("modbus_tcp.tls.private_key " + settings.private_key + " does not belong to " +
                             settings.certificate + " (the key of another certificate?): give the key made with " +
                             "that certificate's request, or the certificate issued for this key");
  }
  const bool used = SSL_CTX_use_PrivateKey(native, key) == 1;
  EVP_PKEY_free(key);
  if (!used) {
    throw std::runtime_error("modbus_tcp.tls.private_key " + settings.private_key +
                             ": cannot be used: " + openssl_error_text());
  }
  if (SSL_CTX_load_verify_locations(native, settings.ca.c_str(), nullptr) != 1) {
    throw std::runtime_error("modbus_tcp.tls.ca " + settings.ca +
                             ": no PEM CA certificate in it: " + openssl_error_text());
  }
  // Tells clients which CAs are accepted, so one with several certificates can pick.
  if (STACK_OF(X509_NAME)* names = SSL_load_client_CA_file(settings.ca.c_str())) {
    SSL_CTX_set_client_CA_list(native, names);
  }
  SSL_CTX_set_verify(native, SSL_VERIFY_PEER | SSL_VERIFY_FAIL_IF_NO_PEER_CERT, remember_refused_certificate);
  ERR_clear_error();
  return context;
}

TlsService::TlsService(const config::TlsConfig& settings, const RolePolicy& policy, RequestHandler& router)
    : settings_(settings), router_(router), policy_(policy), context_(make_tls_context(settings)) {
  certificate_expiry_ = describe_context();
}

std::string TlsService::describe_context() const {
  X509* certificate = SSL_CTX_get0_certificate(context_->native_handle());
  if (certificate == nullptr) return "?";
  return name_text(X509_get_subject_name(certificate)) + ", valid until " + time_text(X509_get0_notAfter(certificate));
}

std::shared_ptr<ssl::context> TlsService::context() const {
  std::lock_guard lock(mutex_);
  return context_;
}

bool TlsService::reload() {
  std::shared_ptr<ssl::context> fresh;
  try {
    fresh = make_tls_context(settings_);
  } catch (const std::exception& error) {
    std::lock_guard lock(mutex_);
    ++stats_.reloads_failed;
    spdlog::error("modbus tcp security: reload failed, the previous certificate, key and CA stay in use: {}",
                  error.what());
    return false;
  }
  std::string description;
  {
    std::lock_guard lock(mutex_);
    context_ = std::move(fresh);
    ++stats_.reloads_ok;
    description = describe_context();
  }
  spdlog::info("modbus tcp security: reloaded {}, {} and CA {}: new handshakes use them (certificate {})",
               settings_.certificate, settings_.private_key, settings_.ca, description);
  return true;
}

std::unique_ptr<RequestHandler> TlsService::admit(SSL* ssl, const std::string& peer) {
  X509* certificate = SSL_get0_peer_certificate(ssl);
  const PeerCertificate client = read_certificate(certificate);
  const RoleDecision decision = role_for(settings_, client);
  if (decision.role == Role::None) {
    count("no_role");
    spdlog::warn("modbus tcp security: refused {} ({}): no role: {}", peer, client.subject, decision.source);
    return nullptr;
  }
  count("ok");
  {
    std::lock_guard lock(mutex_);
    ++stats_.open_connections;
  }
  const std::string role(config::to_string(decision.role));
  spdlog::info("modbus tcp security: {} connected as {} ({}; role {} from {}; {})", peer, client.subject,
               SSL_get_version(ssl), role, decision.source, SSL_get_cipher_name(ssl));
  return std::make_unique<RoleGate>(policy_, decision.role,
                                    "modbus tcp security: " + peer + " (" + client.subject + ", role " + role + ")",
                                    &refusals_, router_);
}

void TlsService::handshake_failed(const boost::system::error_code& error, SSL* ssl, const std::string& peer) {
  std::string_view result = "failed";
  std::string reason = error.message();
  const long verify = ssl != nullptr ? SSL_get_verify_result(ssl) : X509_V_OK;
  if (verify != X509_V_OK) {
    result = result_of_verify_error(verify);
    reason = std::string("certificate verification failed: ") + X509_verify_cert_error_string(verify);
    if (const auto* text = static_cast<const std::string*>(SSL_get_ex_data(ssl, refused_text_index()))) {
      reason += " (" + *text + ")";
    }
  } else if (error.category() == boost::asio::error::get_ssl_category()) {
    result = result_of_ssl_reason(ERR_GET_REASON(static_cast<unsigned long>(error.value())));
    if (result == "not_tls") reason += ": the client does not speak TLS (plain Modbus TCP on the TLS port?)";
    if (result == "no_certificate") reason = "the client sent no certificate (one is required)";
  } else if (error == boost::asio::error::eof || error == boost::asio::ssl::error::stream_truncated) {
    reason = "closed by the client during the handshake";
  }
  count(result);
  refusal_logs_.try_emplace(std::string(result))
      .first->second.warn(fmt::format("modbus tcp security: refused handshake from {}: {} [{}]", peer, reason, result));
}

void TlsService::handshake_closed_by_door(DoorClose why) {
  if (why == DoorClose::Evicted) count("evicted");
  if (why == DoorClose::Deadline) count("timeout");
}

void TlsService::connection_closed() {
  std::lock_guard lock(mutex_);
  if (stats_.open_connections > 0) --stats_.open_connections;
}

void TlsService::count(std::string_view result) {
  std::lock_guard lock(mutex_);
  const std::size_t index = result_index(result);
  if (index < stats_.handshakes.size()) ++stats_.handshakes[index];
}

TlsStats TlsService::stats() const {
  std::lock_guard lock(mutex_);
  TlsStats stats = stats_;
  stats.requests_refused_read = refusals_.of(Role::Read);
  stats.requests_refused_operate = refusals_.of(Role::Operate);
  return stats;
}

}  // namespace sms::gateway
