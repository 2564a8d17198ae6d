// Modbus/TCP Security end to end (docs/SECURITY.md): certificates made by
// the openssl CLI at test time (tests/e2e/make_test_certs.sh), the real sms-gateway with plain
// Modbus TCP off and a TLS listener, the real sms-sim on a pty, and a Boost.Asio SSL client
// with hand-written MBAP framing. Refused handshakes (another CA, expired, not TLS) are logged
// with their reason and peer; each role gets what README's rights table says, and the servo's
// value (read through the simulator's control socket) never changes on a refusal.
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/socket.h>
#include <sys/time.h>

#include <array>
#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <optional>
#include <thread>

#include <boost/asio/connect.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/read.hpp>
#include <boost/asio/ssl.hpp>
#include <boost/asio/write.hpp>

#include "tests/e2e/tls_client.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

namespace asio = boost::asio;
namespace ssl = asio::ssl;
using asio::ip::tcp;

// sts: goal_position is holding register 42 (RAM), max_temperature 13 (EEPROM).
constexpr std::uint16_t kGoalPosition = 42;
constexpr std::uint16_t kMaxTemperature = 13;

Pdu write_register_pdu(std::uint16_t address, std::uint16_t value) {
  return {0x06, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)};
}

Pdu read_registers_pdu(std::uint16_t address, std::uint16_t count) {
  return {0x03, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(count >> 8), static_cast<std::uint8_t>(count)};
}

std::uint16_t free_port() {
  asio::io_context io;
  tcp::acceptor acceptor(io, tcp::endpoint(asio::ip::make_address("127.0.0.1"), 0));
  return acceptor.local_endpoint().port();
}

bool plain_connect_succeeds(std::uint16_t port) {
  asio::io_context io;
  tcp::socket socket(io);
  boost::system::error_code error;
  socket.connect(tcp::endpoint(asio::ip::make_address("127.0.0.1"), port), error);
  return !error;
}

// One gateway on a configuration file with plain Modbus TCP off and TLS on an ephemeral port.
// `extra_tls`: more lines of modbus_tcp.tls, indented by 4.
struct SecureGateway {
  // `extra_tcp`: more lines of modbus_tcp, indented by 2.
  SecureGateway(const TempDir& dir, const std::string& certs, const std::string& pty, std::uint16_t plain_port,
                const std::string& extra_tls = "", const std::string& extra_tcp = "") {
    const std::string yaml =
        "modbus_tcp:\n"
        "  listen: \"127.0.0.1:" +
        std::to_string(plain_port) +
        "\"\n"
        "  plain: false\n" +
        extra_tcp + tls_listener_yaml(certs, "    role_names: {Engineer: engineer}\n" + extra_tls) +
        one_servo_yaml(pty);
    const std::string path = dir.file("secure.yaml");
    std::ofstream(path) << yaml;
    process = std::make_unique<ChildProcess>(
        std::vector<std::string>{bin("sms-gateway"), "--config", path, "--metrics", "127.0.0.1:0"});
    const std::string metrics_marker = "/healthz on http://127.0.0.1:";
    const auto metrics_line = process->wait_for_line(metrics_marker, 15s);
    if (!metrics_line) throw std::runtime_error("sms-gateway did not serve metrics:\n" + process->output());
    metrics_port = static_cast<std::uint16_t>(
        std::stoi(metrics_line->substr(metrics_line->find(metrics_marker) + metrics_marker.size())));
    const std::string marker = "modbus tcp security: listening on 127.0.0.1:";
    const auto line = process->wait_for_line(marker, 15s);
    if (!line) throw std::runtime_error("sms-gateway did not listen for TLS:\n" + process->output());
    port = static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
    if (!process->wait_for_line("servos online", 15s)) {
      throw std::runtime_error("sms-gateway did not report its bus:\n" + process->output());
    }
  }

  // One sample of /metrics, e.g. `sms_gateway_tls_handshakes_total{result="expired"}`.
  std::string metric(const std::string& sample) const {
    const auto response = test::http_request(metrics_port, "GET", "/metrics");
    const auto at = response.body.find("\n" + sample + " ");
    if (at == std::string::npos) return "<absent>";
    const auto start = at + sample.size() + 2;
    return response.body.substr(start, response.body.find('\n', start) - start);
  }

  std::unique_ptr<ChildProcess> process;
  std::uint16_t port = 0;
  std::uint16_t metrics_port = 0;
};

class Tls : public testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir();
    certs_ = dir_->file("certs");
    const std::string command = std::string(SMS_SOURCE_DIR) + "/tests/e2e/make_test_certs.sh " + certs_;
    ASSERT_EQ(std::system(command.c_str()), 0) << command;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }

  void SetUp() override {
    sim_ = std::make_unique<SimProcess>(*dir_, "sim", std::vector<std::string>{"--servo", "1:sts"});
    plain_port_ = free_port();
    gateway_ = std::make_unique<SecureGateway>(*dir_, certs_, sim_->pty(), plain_port_);
    // Polled at least once (facts register 1002 is the cache age; 0xFFFF before the first poll).
    TlsClient client(certs_, "operate", gateway_->port);
    ASSERT_TRUE(eventually([&] {
      const auto answer = client.request({0x04, 0x03, 0xEA, 0x00, 0x01});
      return answer && answer->size() == 4 && (answer->at(2) != 0xFF || answer->at(3) != 0xFF);
    })) << gateway_->process->output();
  }

  std::string log() { return gateway_->process->output(); }
  bool logged(const std::string& text) { return gateway_->process->wait_for_line(text, 5s).has_value(); }

  static TempDir* dir_;
  static std::string certs_;
  std::unique_ptr<SimProcess> sim_;
  std::unique_ptr<SecureGateway> gateway_;
  std::uint16_t plain_port_ = 0;
};

TempDir* Tls::dir_ = nullptr;
std::string Tls::certs_;

TEST_F(Tls, PlainDisabledLeavesNothingOnThePlainPort) {
  EXPECT_FALSE(plain_connect_succeeds(plain_port_)) << "something listens on the plain port " << plain_port_;
  EXPECT_TRUE(logged("plain Modbus TCP is off"));
}

TEST_F(Tls, CheckConfigLoadsTheTlsFiles) {
  ChildProcess ok({bin("sms-gateway"), "--check-config", dir_->file("secure.yaml")});
  EXPECT_EQ(ok.wait_exit(10s), 0) << ok.output();
  const std::string broken = dir_->file("broken.yaml");
  std::ofstream(broken) << substitute(
      [&] {
        std::ifstream in(dir_->file("secure.yaml"));
        return std::string(std::istreambuf_iterator<char>(in), {});
      }(),
      "/server.key", "/read.key");
  ChildProcess refused({bin("sms-gateway"), "--check-config", broken});
  EXPECT_EQ(refused.wait_exit(10s), 2);
  // The key of another certificate is said to be that, not "not a PEM private key".
  EXPECT_NE(refused.output().find("modbus_tcp.tls.private_key " + certs_ + "/read.key does not belong to " + certs_ +
                                  "/server.crt"),
            std::string::npos)
      << refused.output();
  EXPECT_EQ(refused.output().find("not an unencrypted PEM private key"), std::string::npos) << refused.output();
}

TEST_F(Tls, RoleExtensionOfAnotherSchemeFallsBackToTheCnMapping) {
  // The extension says `Operator`; roles: {plc-3: operate} maps the certificate by its CN.
  TlsClient plc(certs_, "other-scheme", gateway_->port);
  // Repeated only if the bus missed an answer (0x0B on a loaded machine); a role refusal would
  // be 0x01 or 0x02 every time.
  EXPECT_TRUE(eventually([&] {
    const auto move = plc.request(write_register_pdu(kGoalPosition, 2500));
    return move && *move == write_register_pdu(kGoalPosition, 2500);
  })) << log();
  EXPECT_TRUE(eventually([&] { return sim_->field(1, "goal_position") == 2500; }));
  const auto line = gateway_->process->wait_for_line("connected as CN=plc-3", 5s);
  ASSERT_TRUE(line) << log();
  EXPECT_NE(line->find("role operate from role extension `Operator` not in role_names, so roles[plc-3] (CN)"),
            std::string::npos)
      << *line;
}

TEST_F(Tls, RoleExtensionNamedInRoleNamesGetsThatRole) {
  // The extension says `Engineer`; role_names: {Engineer: engineer}.
  TlsClient engineer(certs_, "named-role", gateway_->port);
  const long temperature = sim_->field(1, "max_temperature");
  const auto target = static_cast<std::uint16_t>(temperature - 3);
  const auto answer = engineer.request(write_register_pdu(kMaxTemperature, target));
  ASSERT_TRUE(answer) << log();
  EXPECT_EQ(*answer, write_register_pdu(kMaxTemperature, target));
  EXPECT_TRUE(eventually([&] { return sim_->field(1, "max_temperature") == target; }));
  EXPECT_TRUE(logged("role engineer from role extension `Engineer` (role_names)")) << log();
}

TEST_F(Tls, CriticalRoleExtensionIsHandled) {
  TlsClient plc(certs_, "critical", gateway_->port);
  EXPECT_TRUE(eventually([&] {  // as above: only a missed bus answer is retried
    const auto move = plc.request(write_register_pdu(kGoalPosition, 1800));
    return move && *move == write_register_pdu(kGoalPosition, 1800);
  })) << log();
  EXPECT_TRUE(logged("connected as CN=plc-4,O=Test Plant")) << log();
  EXPECT_EQ(gateway_->metric("sms_gateway_tls_handshakes_total{result=\"bad_certificate\"}"), "0");
}

TEST_F(Tls, AnotherUnhandledCriticalExtensionIsStillRefused) {
  TlsClient plc(certs_, "critical-other", gateway_->port);
  EXPECT_FALSE(plc.request(read_registers_pdu(kGoalPosition, 1)));
  const auto line = gateway_->process->wait_for_line("refused handshake from 127.0.0.1:", 5s);
  ASSERT_TRUE(line) << log();
  EXPECT_NE(line->find("unhandled critical extension"), std::string::npos) << *line;
  EXPECT_NE(line->find("[bad_certificate]"), std::string::npos) << *line;
}

TEST_F(Tls, OpenSslClientWithTheCriticalRoleExtensionIsServed) {
  // An independent client: openssl s_client sends one Modbus read and prints what came back.
  const std::string request = dir_->file("request.bin");
  std::ofstream(request, std::ios::binary) << std::string("\x00\x07\x00\x00\x00\x06\x01\x03\x00\x2A\x00\x01", 12);
  const std::string answer = dir_->file("answer.bin");
  const std::string command = "(cat " + request +
                              "; sleep 1) | timeout 10 openssl s_client -quiet -no_ign_eof -connect 127.0.0.1:" +
                              std::to_string(gateway_->port) + " -CAfile " + certs_ + "/ca.crt -cert " + certs_ +
                              "/critical.crt -key " + certs_ + "/critical.key > " + answer + " 2>/dev/null";
  std::system(command.c_str());
  std::ifstream in(answer, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  ASSERT_EQ(bytes.size(), 11u) << log();
  EXPECT_EQ(bytes.substr(0, 2), std::string("\x00\x07", 2));
  EXPECT_EQ(static_cast<std::uint8_t>(bytes[7]), 0x03);
}

TEST_F(Tls, CertificateOfAnotherCaIsRefusedAndLogged) {
  TlsClient client(certs_, "foreign", gateway_->port);
  EXPECT_FALSE(client.request(read_registers_pdu(kGoalPosition, 1)));
  const auto line = gateway_->process->wait_for_line("refused handshake from 127.0.0.1:", 5s);
  ASSERT_TRUE(line) << log();
  EXPECT_NE(line->find("[unknown_ca]"), std::string::npos) << *line;
  EXPECT_NE(line->find("CN=plc-9"), std::string::npos) << *line;
  EXPECT_EQ(gateway_->metric("sms_gateway_tls_handshakes_total{result=\"unknown_ca\"}"), "1");
}

TEST_F(Tls, ExpiredCertificateIsRefusedAndLogged) {
  TlsClient client(certs_, "expired", gateway_->port);
  EXPECT_FALSE(client.request(write_register_pdu(kGoalPosition, 1000)));
  const auto line = gateway_->process->wait_for_line("refused handshake from 127.0.0.1:", 5s);
  ASSERT_TRUE(line) << log();
  EXPECT_NE(line->find("certificate has expired"), std::string::npos) << *line;
  EXPECT_NE(line->find("[expired]"), std::string::npos) << *line;
  EXPECT_EQ(gateway_->metric("sms_gateway_tls_handshakes_total{result=\"expired\"}"), "1");
}

TEST_F(Tls, CertificateWithoutRoleIsRefused) {
  TlsClient client(certs_, "norole", gateway_->port);
  EXPECT_FALSE(client.request(read_registers_pdu(kGoalPosition, 1)));
  EXPECT_TRUE(logged("(CN=stranger,O=Test Plant): no role")) << log();
}

TEST_F(Tls, GarbageInsteadOfTlsClosesTheConnectionAndTheGatewayGoesOn) {
  {
    asio::io_context io;
    tcp::socket socket(io);
    socket.connect(tcp::endpoint(asio::ip::make_address("127.0.0.1"), gateway_->port));
    set_receive_timeout(socket.native_handle());
    // A plain Modbus request on the TLS port, then noise.
    const Pdu garbage{0x00, 0x01, 0x00, 0x00, 0x00, 0x06, 0x01, 0x03, 0x00, 0x2A, 0x00, 0x01, 0xDE, 0xAD, 0xBE, 0xEF};
    asio::write(socket, asio::buffer(garbage));
    std::array<std::uint8_t, 64> buffer{};
    boost::system::error_code error;
    socket.read_some(asio::buffer(buffer), error);
    EXPECT_EQ(error, asio::error::eof) << error.message();
  }
  const auto line = gateway_->process->wait_for_line("refused handshake from 127.0.0.1:", 5s);
  ASSERT_TRUE(line) << log();
  EXPECT_NE(line->find("[not_tls]"), std::string::npos) << *line;
  EXPECT_EQ(gateway_->metric("sms_gateway_tls_handshakes_total{result=\"not_tls\"}"), "1");
  TlsClient client(certs_, "operate", gateway_->port);
  const auto answer = client.request(read_registers_pdu(kGoalPosition, 1));
  ASSERT_TRUE(answer);
  EXPECT_EQ(answer->at(0), 0x03);
}

TEST_F(Tls, ReadRoleReadsButItsWriteIsAnsweredIllegalFunctionAndNothingChanges) {
  const long before = sim_->field(1, "goal_position");
  for (const std::string name : {"read", "mapped"}) {  // role extension; roles: {hmi-2.plant: read}
    TlsClient hmi(certs_, name, gateway_->port);
    const auto read = hmi.request(read_registers_pdu(kGoalPosition, 1));
    ASSERT_TRUE(read) << name << "\n" << log();
    EXPECT_EQ(read->at(0), 0x03) << name;
    const auto write = hmi.request(write_register_pdu(kGoalPosition, static_cast<std::uint16_t>(before + 500)));
    ASSERT_TRUE(write) << name;
    EXPECT_EQ(*write, (Pdu{0x86, 0x01})) << name;
  }
  std::this_thread::sleep_for(100ms);
  EXPECT_EQ(sim_->field(1, "goal_position"), before);
  EXPECT_TRUE(logged("role read may only read"));
  EXPECT_EQ(gateway_->metric("sms_gateway_tls_requests_refused_total{role=\"read\"}"), "2");
}

TEST_F(Tls, OperateRoleMovesTheServoButCannotWriteEeprom) {
  TlsClient plc(certs_, "operate", gateway_->port);
  const auto move = plc.request(write_register_pdu(kGoalPosition, 3000));
  ASSERT_TRUE(move) << log();
  EXPECT_EQ(*move, write_register_pdu(kGoalPosition, 3000));
  EXPECT_TRUE(eventually([&] { return sim_->field(1, "goal_position") == 3000; }));
  EXPECT_TRUE(eventually([&] { return std::abs(sim_->field(1, "present_position") - 3000) < 50; }));

  const long temperature = sim_->field(1, "max_temperature");
  const auto eeprom = plc.request(write_register_pdu(kMaxTemperature, static_cast<std::uint16_t>(temperature - 5)));
  ASSERT_TRUE(eeprom);
  EXPECT_EQ(*eeprom, (Pdu{0x86, 0x02}));
  // Mid-point calibration (torque_enable := 128) is the engineer's too.
  const auto calibrate = plc.request(write_register_pdu(40, 128));
  ASSERT_TRUE(calibrate);
  EXPECT_EQ(*calibrate, (Pdu{0x86, 0x02}));
  std::this_thread::sleep_for(100ms);
  EXPECT_EQ(sim_->field(1, "max_temperature"), temperature);
  EXPECT_TRUE(logged("needs role engineer"));
}

TEST_F(Tls, EngineerRoleWritesAnEepromField) {
  TlsClient engineer(certs_, "engineer", gateway_->port);
  const long temperature = sim_->field(1, "max_temperature");
  const auto target = static_cast<std::uint16_t>(temperature - 5);
  const auto answer = engineer.request(write_register_pdu(kMaxTemperature, target));
  ASSERT_TRUE(answer) << log();
  EXPECT_EQ(*answer, write_register_pdu(kMaxTemperature, target));
  EXPECT_TRUE(eventually([&] { return sim_->field(1, "max_temperature") == target; }));
}

TEST_F(Tls, SighupReloadsTheFilesAndAFailedReloadKeepsTheOldOnes) {
  // The gateway's files are replaced by those of CA 2 and reloaded: clients of CA 2 get in,
  // clients of the old CA no longer do.
  namespace fs = std::filesystem;
  const std::string live = dir_->file("live");
  fs::create_directories(live);
  for (const std::string file : {"ca.crt", "server.crt", "server.key", "ca.key"}) {
    fs::copy_file(certs_ + "/" + file, live + "/" + file, fs::copy_options::overwrite_existing);
  }
  for (const std::string name : {"operate", "ca2-operate"}) {
    fs::copy_file(certs_ + "/" + name + ".crt", live + "/" + name + ".crt", fs::copy_options::overwrite_existing);
    fs::copy_file(certs_ + "/" + name + ".key", live + "/" + name + ".key", fs::copy_options::overwrite_existing);
  }
  fs::copy_file(certs_ + "/ca2.crt", live + "/ca2.crt", fs::copy_options::overwrite_existing);
  gateway_.reset();
  gateway_ = std::make_unique<SecureGateway>(*dir_, live, sim_->pty(), free_port());
  {
    TlsClient before(live, "operate", gateway_->port);
    ASSERT_TRUE(before.request(read_registers_pdu(kGoalPosition, 1))) << log();
  }

  // A reload that fails (the key is not PEM) keeps the old context.
  std::ofstream(live + "/server.key") << "not a key\n";
  gateway_->process->signal(SIGHUP);
  const auto failed = gateway_->process->wait_for_line("reload failed", 5s);
  ASSERT_TRUE(failed) << log();
  EXPECT_NE(failed->find("private_key"), std::string::npos) << *failed;
  {
    TlsClient still(live, "operate", gateway_->port);
    EXPECT_TRUE(still.request(read_registers_pdu(kGoalPosition, 1))) << log();
  }

  fs::copy_file(certs_ + "/server2.crt", live + "/server.crt", fs::copy_options::overwrite_existing);
  fs::copy_file(certs_ + "/server2.key", live + "/server.key", fs::copy_options::overwrite_existing);
  fs::copy_file(certs_ + "/ca2.crt", live + "/ca.crt", fs::copy_options::overwrite_existing);
  gateway_->process->signal(SIGHUP);
  ASSERT_TRUE(gateway_->process->wait_for_line("modbus tcp security: reloaded", 5s)) << log();
  {
    TlsClient renewed(live, "ca2-operate", gateway_->port, "ca2");
    const auto answer = renewed.request(read_registers_pdu(kGoalPosition, 1));
    ASSERT_TRUE(answer) << log();
    EXPECT_EQ(answer->at(0), 0x03);
  }
  {
    TlsClient old(live, "operate", gateway_->port, "ca2");
    EXPECT_FALSE(old.request(read_registers_pdu(kGoalPosition, 1)));
  }
}

// The gateway ends a TLS connection with close_notify (RFC 8446 6.1), seen by Python's ssl
// module: after the client's own close_notify in TLS 1.2, when it refuses a certificate without
// a role, and at the idle timeout.
std::string close_notify_case(std::uint16_t port, const std::string& certs, const std::string& which) {
  ChildProcess client({"/usr/bin/python3", std::string(SMS_SOURCE_DIR) + "/tests/e2e/tls_close_notify.py",
                       std::to_string(port), certs, which});
  const auto status = client.wait_exit(30s);
  if (!status) return "exit (none: still running after 30 s): " + client.output();
  return (*status == 0 ? std::string() : "exit " + std::to_string(*status) + ": ") + client.output();
}

TEST_F(Tls, ClientsCloseNotifyIsAnsweredWithTheGatewaysOwn) {
  const std::string outcome = close_notify_case(gateway_->port, certs_, "client-closes");
  EXPECT_NE(outcome.find("the gateway answered close_notify"), std::string::npos) << outcome << log();
  EXPECT_EQ(outcome.find("exit "), std::string::npos) << outcome;
}

TEST_F(Tls, RefusalOfACertificateWithoutRoleEndsWithCloseNotify) {
  const std::string outcome = close_notify_case(gateway_->port, certs_, "no-role");
  EXPECT_NE(outcome.find("closed with close_notify"), std::string::npos) << outcome << log();
}

TEST_F(Tls, IdleTimeoutEndsWithCloseNotify) {
  gateway_.reset();
  gateway_ = std::make_unique<SecureGateway>(*dir_, certs_, sim_->pty(), free_port(), "", "  idle_timeout_s: 1\n");
  const std::string outcome = close_notify_case(gateway_->port, certs_, "idle");
  EXPECT_NE(outcome.find("closed with close_notify"), std::string::npos) << outcome << log();
}

TEST_F(Tls, ServedConnectionsOverTheLimitAreRefusedAndCountedForTheTlsListener) {
  // The same configuration with max_connections: 1 (on the TLS listener it counts served
  // connections, not handshakes).
  const std::string file = dir_->file("limited.yaml");
  {
    std::ifstream in(dir_->file("secure.yaml"));
    const std::string yaml((std::istreambuf_iterator<char>(in)), {});
    std::ofstream(file) << substitute(yaml, "  plain: false\n", "  plain: false\n  max_connections: 1\n");
  }
  gateway_.reset();  // the simulator's line is for one gateway at a time
  ChildProcess limited({bin("sms-gateway"), "--config", file, "--metrics", "127.0.0.1:0"});
  const std::string metrics_marker = "/healthz on http://127.0.0.1:";
  const auto metrics_line = limited.wait_for_line(metrics_marker, 15s);
  ASSERT_TRUE(metrics_line) << limited.output();
  const auto metrics_port = static_cast<std::uint16_t>(
      std::stoi(metrics_line->substr(metrics_line->find(metrics_marker) + metrics_marker.size())));
  const std::string marker = "modbus tcp security: listening on 127.0.0.1:";
  const auto line = limited.wait_for_line(marker, 15s);
  ASSERT_TRUE(line) << limited.output();
  const auto port = static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));

  TlsClient first(certs_, "read", port);
  ASSERT_TRUE(first.request(read_registers_pdu(kGoalPosition, 1))) << limited.output();
  {
    TlsClient second(certs_, "operate", port);
    EXPECT_FALSE(second.request(read_registers_pdu(kGoalPosition, 1)));
  }
  const auto refusal = limited.wait_for_line("modbus tcp security: refusing connection from 127.0.0.1:", 5s);
  ASSERT_TRUE(refusal) << limited.output();
  EXPECT_NE(refusal->find(": 1 connections served, the limit (modbus_tcp.max_connections)"), std::string::npos)
      << *refusal;
  const auto body = test::http_request(metrics_port, "GET", "/metrics").body;
  EXPECT_NE(body.find("sms_gateway_tcp_connections_refused_total{listener=\"tls\",reason=\"max_connections\"} 1"),
            std::string::npos)
      << body;
  EXPECT_NE(body.find("sms_gateway_tcp_connections_refused_total{listener=\"plain\",reason=\"max_connections\"} 0"),
            std::string::npos)
      << body;
  // The first client is still served.
  EXPECT_TRUE(first.request(read_registers_pdu(kGoalPosition, 1)));
}

}  // namespace
}  // namespace sms::e2e
