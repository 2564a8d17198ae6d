#include "gateway/console/console_tls.h"

#include "gateway/modbus_tcp/tls.h"

#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <stdexcept>

namespace sms::gateway::console {

namespace {

constexpr const char* kMakeOne =
    "make a pair with `openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 "
    "-subj /CN=$(hostname) -keyout console.key -out console.crt` (docs/CONSOLE.md \"HTTPS\")";

void check_readable(const char* setting, const std::string& path) {
  if (!std::ifstream(path, std::ios::binary)) {
    throw std::runtime_error(std::string(setting) + " " + path + ": cannot open: " + std::strerror(errno) +
                             " (the gateway runs as the service user: the file must be readable by its group); or " +
                             kMakeOne);
  }
}

}  // namespace

std::shared_ptr<boost::asio::ssl::context> console_tls_context(const std::string& certificate, const std::string& key) {
  check_readable("console.certificate", certificate);
  check_readable("console.key", key);
  auto context = std::make_shared<boost::asio::ssl::context>(boost::asio::ssl::context::tls_server);
  SSL_CTX* native = context->native_handle();
  ERR_clear_error();
  SSL_CTX_set_min_proto_version(native, TLS1_2_VERSION);
  SSL_CTX_set_options(native, SSL_OP_NO_RENEGOTIATION | SSL_OP_CIPHER_SERVER_PREFERENCE);
  if (SSL_CTX_use_certificate_chain_file(native, certificate.c_str()) != 1) {
    throw std::runtime_error("console.certificate " + certificate + ": not a PEM certificate: " + openssl_error_text() +
                             "; " + kMakeOne);
  }
  // Read first and matched apart: the error of a key of another certificate would otherwise read
  // as if the file were no key at all.
  BIO* file = BIO_new_file(key.c_str(), "r");
  EVP_PKEY* pkey = file == nullptr ? nullptr
                                   : PEM_read_bio_PrivateKey(
                                         file, nullptr, [](char*, int, int, void*) { return 0; }, nullptr);
  if (file != nullptr) BIO_free(file);
  if (pkey == nullptr) {
    throw std::runtime_error("console.key " + key + ": not an unencrypted PEM private key: " + openssl_error_text());
  }
  const bool matches = X509_check_private_key(SSL_CTX_get0_certificate(native), pkey) == 1;
  ERR_clear_error();
  const bool used = matches && SSL_CTX_use_PrivateKey(native, pkey) == 1;
  EVP_PKEY_free(pkey);
  if (!matches) {
    throw std::runtime_error("console.key " + key + " does not belong to " + certificate +
                             " (the key of another certificate?): give the key made with that certificate, or a "
                             "certificate made for this key");
  }
  if (!used) throw std::runtime_error("console.key " + key + ": cannot be used: " + openssl_error_text());
  return context;
}

}  // namespace sms::gateway::console
