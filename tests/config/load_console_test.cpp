// console: HTTPS for password users off loopback (its own certificate and key, or tls), the
// rules that go with it, each rejection's message and place, and the dump that loads back the same.
#include <gtest/gtest.h>

#include <string>

#include "config/load.h"
#include "tests/config/config_test_support.h"

namespace sms::config {
namespace {

using testing::error_text;
using testing::kBusAndServo;

const std::string kUser =
    "  users:\n    - {name: shift, role: operate, password_hash: "
    "\"$argon2id$v=19$m=65536,t=2,p=1$c29tZXNhbHQ$aGFzaA\"}\n";
const std::string kModbusTls =
    "modbus_tcp:\n  tls: {listen: \"0.0.0.0:802\", certificate: /etc/tls/gw.crt, private_key: /etc/tls/gw.key, "
    "ca: /etc/tls/ca.crt}\n";

std::string console(const std::string& keys) { return kBusAndServo + "console:\n" + keys + kUser; }

TEST(LoadConsole, OwnCertificateAndKeyServeHttpsAndDumpBackTheSame) {
  const auto config = load_config_string(console("  listen: 0.0.0.0:8443\n"
                                                 "  certificate: /etc/sms-gateway/console/console.crt\n"
                                                 "  key: /etc/sms-gateway/console/console.key\n"),
                                         "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  EXPECT_EQ(config->console->certificate, "/etc/sms-gateway/console/console.crt");
  EXPECT_EQ(config->console->key, "/etc/sms-gateway/console/console.key");
  EXPECT_FALSE(config->console->tls);
  EXPECT_FALSE(config->console->insecure_http);
  EXPECT_TRUE(config->console->https());
  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string() << "\n" << dump_config(*config);
  EXPECT_EQ(*again, *config);
}

TEST(LoadConsole, PasswordUsersOffLoopbackNeedHttps) {
  EXPECT_EQ(error_text(console("  listen: 0.0.0.0:8080\n")),
            "plant.yaml:6:3: console.listen: 0.0.0.0:8080 is reachable from other machines and the console's users "
            "log in with passwords, which plain HTTP would carry in clear across the network: give the console a "
            "certificate and key (console.certificate and console.key; the Debian package makes a self-signed pair "
            "in /etc/sms-gateway/console/), or tls: true with modbus_tcp.tls, or listen on 127.0.0.1. "
            "insecure_http: true serves plain HTTP anyway (a warning at every start)");
  // On a loopback address the passwords stay on this machine: plain HTTP is fine.
  EXPECT_EQ(error_text(console("  listen: 127.0.0.1:8080\n")), "<loaded>");
  EXPECT_EQ(error_text(console("  listen: \"[::1]:8080\"\n")), "<loaded>");
  // Modbus/TCP Security's files serve HTTPS too.
  EXPECT_EQ(error_text(kModbusTls + console("  listen: 0.0.0.0:8443\n  tls: true\n")), "<loaded>");
}

TEST(LoadConsole, InsecureHttpIsAcceptedWhenSaidSo) {
  const auto config = load_config_string(console("  listen: 0.0.0.0:8080\n  insecure_http: true\n"), "plant.yaml");
  ASSERT_TRUE(config) << config.error().to_string();
  EXPECT_TRUE(config->console->insecure_http);
  EXPECT_FALSE(config->console->https());
  const auto again = load_config_string(dump_config(*config), "dump.yaml");
  ASSERT_TRUE(again) << again.error().to_string();
  EXPECT_EQ(*again, *config);
}

TEST(LoadConsole, CertificateAndKeyGoTogether) {
  EXPECT_EQ(error_text(console("  listen: 0.0.0.0:8443\n  certificate: /c.crt\n")),
            "plant.yaml:7:16: console.certificate: needs console.key too (the certificate's private key, PEM, "
            "unencrypted)");
  EXPECT_EQ(error_text(console("  listen: 0.0.0.0:8443\n  key: /c.key\n")),
            "plant.yaml:7:8: console.key: needs console.certificate too (the certificate of this key, PEM)");
  EXPECT_EQ(error_text(console("  certificate: \"\"\n  key: /c.key\n")),
            "plant.yaml:6:16: console.certificate: must not be empty");
}

TEST(LoadConsole, OwnCertificateOrTlsNotBoth) {
  EXPECT_EQ(error_text(kModbusTls + console("  tls: true\n  certificate: /c.crt\n  key: /c.key\n")),
            "plant.yaml:9:16: console.certificate: tls: true already serves HTTPS, with modbus_tcp.tls's "
            "certificate and client certificates; give either tls: true or certificate and key (the console's "
            "own, for password users), not both");
}

TEST(LoadConsole, InsecureHttpWithHttpsIsRefused) {
  EXPECT_EQ(error_text(console("  certificate: /c.crt\n  key: /c.key\n  insecure_http: true\n")),
            "plant.yaml:8:18: console.insecure_http: true, but the console serves HTTPS (certificate and key); "
            "remove insecure_http");
  EXPECT_EQ(error_text(kModbusTls + console("  tls: true\n  insecure_http: true\n")),
            "plant.yaml:9:18: console.insecure_http: true, but the console serves HTTPS (tls: true); remove "
            "insecure_http");
  EXPECT_EQ(error_text(console("  insecure_http: maybe\n")),
            "plant.yaml:6:18: console.insecure_http: expected true or false, got `maybe`");
}

TEST(LoadConsole, WithoutUsersOrTlsOnlyLoopback) {
  // The rule from before: a console that cannot tell who asks serves this machine only; a
  // certificate alone does not tell who asks either.
  EXPECT_NE(error_text(kBusAndServo + "console: {listen: 0.0.0.0:8443, certificate: /c.crt, key: /c.key}\n")
                .find("with neither users nor tls the console has no way to know who asks"),
            std::string::npos);
}

// Loopback in every form a listen address takes: IPv4, IPv6, an IPv4 address in IPv6 form.
TEST(LoadConsole, LoopbackIsKnownInEveryForm) {
  for (const char* host :
       {"127.0.0.1", "127.1.2.3", "localhost", "::1", "[::1]", "::ffff:127.0.0.1", "[::ffff:127.0.0.1]"}) {
    EXPECT_TRUE(is_loopback_host(host)) << host;
  }
  for (const char* host : {"0.0.0.0", "::", "[::]", "192.168.1.20", "::ffff:192.168.1.20", "128.0.0.1"}) {
    EXPECT_FALSE(is_loopback_host(host)) << host;
  }
}

}  // namespace
}  // namespace sms::config
