// The front door every TCP listener shares (gateway/net/door.h), tried the same way on all four:
// plain Modbus TCP, Modbus/TCP Security, the browser console and /metrics, in one sms-gateway on
// the simulator. Floods of connections that are silent, that send half of their first message,
// or that send a whole first message (a TLS ClientHello, an MBAP header, HTTP headers) and then
// nothing more — kept open and re-opened as soon as the gateway closes them, from other
// addresses of 127/8 or from the prober's own — must never keep a real client out: every probe
// is served, the door counts what it closed in /metrics, and a connection that never completes
// its first request is closed at the deadline.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <openssl/bio.h>
#include <openssl/ssl.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <memory>
#include <thread>
#include <vector>

#include "tests/e2e/tls_client.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using namespace std::chrono_literals;

enum class Way { Plain, Tls, Console, Metrics };
std::string listener_label(Way way);
// For GoogleTest's names and messages.
void PrintTo(Way way, std::ostream* out) { *out << listener_label(way); }

std::string listener_label(Way way) {
  switch (way) {
    case Way::Plain: return "plain";
    case Way::Tls: return "tls";
    case Way::Console: return "console";
    case Way::Metrics: return "metrics";
  }
  return "?";
}

// The bytes a real TLS client sends first: one whole ClientHello record, from OpenSSL itself.
std::string client_hello() {
  SSL_CTX* context = SSL_CTX_new(TLS_client_method());
  SSL* ssl = SSL_new(context);
  BIO* in = BIO_new(BIO_s_mem());
  BIO* out = BIO_new(BIO_s_mem());
  SSL_set_bio(ssl, in, out);
  SSL_set_connect_state(ssl);
  SSL_do_handshake(ssl);  // wants to read the server's answer: the hello is written
  std::string hello(static_cast<std::size_t>(BIO_pending(out)), '\0');
  BIO_read(out, hello.data(), static_cast<int>(hello.size()));
  SSL_free(ssl);
  SSL_CTX_free(context);
  return hello;
}

// What an attacking connection sends once it is open.
enum class Attack { Silent, Partial, FullHello };

std::string attack_bytes(Way way, Attack attack) {
  if (attack == Attack::Silent) return {};
  switch (way) {
    case Way::Plain:
      // Three bytes of an MBAP header; or the whole header announcing a PDU that never comes.
      return attack == Attack::Partial ? std::string("\x00\x01\x00", 3)
                                       : std::string("\x00\x01\x00\x00\x00\x06\xFF\x04", 8);
    case Way::Tls: {
      const std::string hello = client_hello();
      return attack == Attack::Partial ? hello.substr(0, 10) : hello;
    }
    case Way::Console:
    case Way::Metrics:
      // A request line alone; or whole headers announcing a body that never comes.
      return attack == Attack::Partial
                 ? std::string("GET /login HTTP/1.1\r\n")
                 : std::string(
                       "POST /api/login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                       "Content-Length: 64\r\n\r\n");
  }
  return {};
}

// Holds `count` connections to the port open, each having sent `bytes`, from the given source
// addresses in turn (all of 127/8 is this machine), and opens a new one each time the gateway
// closes one; until destroyed.
class Flood {
 public:
  Flood(std::uint16_t port, std::vector<std::string> sources, std::size_t count, std::string bytes)
      : port_(port), sources_(std::move(sources)), bytes_(std::move(bytes)), fds_(count, -1) {
    for (std::size_t i = 0; i < fds_.size(); ++i) fds_[i] = open(i);
    thread_ = std::thread([this] { run(); });
  }
  ~Flood() {
    stop_ = true;
    thread_.join();
    for (const int fd : fds_) {
      if (fd >= 0) ::close(fd);
    }
  }
  Flood(const Flood&) = delete;
  Flood& operator=(const Flood&) = delete;

  std::uint64_t reopened() const { return reopened_; }

 private:
  int open(std::size_t index) const {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (fd < 0) return -1;
    const int one = 1;
    ::setsockopt(fd, IPPROTO_IP, IP_BIND_ADDRESS_NO_PORT, &one, sizeof one);
    sockaddr_in source{};
    source.sin_family = AF_INET;
    ::inet_pton(AF_INET, sources_[index % sources_.size()].c_str(), &source.sin_addr);
    sockaddr_in target{};
    target.sin_family = AF_INET;
    target.sin_port = htons(port_);
    ::inet_pton(AF_INET, "127.0.0.1", &target.sin_addr);
    if (::bind(fd, reinterpret_cast<sockaddr*>(&source), sizeof source) != 0 ||
        ::connect(fd, reinterpret_cast<sockaddr*>(&target), sizeof target) != 0 ||
        (!bytes_.empty() && ::send(fd, bytes_.data(), bytes_.size(), MSG_NOSIGNAL) < 0)) {
      ::close(fd);
      return -1;
    }
    return fd;
  }

  void run() {
    std::vector<pollfd> polled(fds_.size());
    while (!stop_) {
      for (std::size_t i = 0; i < fds_.size(); ++i) {
        if (fds_[i] < 0) fds_[i] = open(i);  // refused or failed: try again next round
        polled[i] = pollfd{fds_[i], POLLIN | POLLRDHUP, 0};
      }
      if (::poll(polled.data(), polled.size(), 10) <= 0) continue;
      for (std::size_t i = 0; i < fds_.size(); ++i) {
        if (polled[i].revents == 0) continue;
        // What the gateway answers (a ServerHello, an error page) is read and dropped; only its
        // close makes room for the next connection.
        char sink[4096];
        if ((polled[i].revents & (POLLRDHUP | POLLHUP | POLLERR)) == 0 && ::recv(fds_[i], sink, sizeof sink, 0) > 0) {
          continue;
        }
        ::close(fds_[i]);
        fds_[i] = open(i);
        ++reopened_;
      }
      std::this_thread::sleep_for(1ms);
    }
  }

  const std::uint16_t port_;
  const std::vector<std::string> sources_;
  const std::string bytes_;
  std::vector<int> fds_;
  std::atomic<bool> stop_{false};
  std::atomic<std::uint64_t> reopened_{0};
  std::thread thread_;
};

std::vector<std::string> addresses(int first, int last) {
  std::vector<std::string> list;
  for (int i = first; i <= last; ++i) list.push_back("127.0.0." + std::to_string(i));
  return list;
}

// "Served within 1 s" is the functional bound; sanitizer builds run several times slower.
#if defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(undefined_behavior_sanitizer)
constexpr auto kServedWithin = 5s;
#else
constexpr auto kServedWithin = 1s;
#endif
#else
constexpr auto kServedWithin = 1s;
#endif

// A port nothing listens on now (the plain and TLS listeners may not both ask for port 0).
std::uint16_t free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  ::inet_pton(AF_INET, "127.0.0.1", &address.sin_addr);
  socklen_t size = sizeof address;
  ::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &size);
  ::close(fd);
  return ntohs(address.sin_port);
}

// One sms-gateway with all four listeners on ports of its choosing; the deadlines that can be
// configured (plain and TLS) set to 1 s so the deadline tests are short.
class FourDoors {
 public:
  FourDoors(const TempDir& dir, const std::string& certs, const std::string& pty) : certs_(certs) {
    const std::string yaml =
        "modbus_tcp:\n"
        "  listen: \"127.0.0.1:" +
        std::to_string(free_port()) +
        "\"\n"
        "  first_request_timeout_ms: 1000\n" +
        tls_listener_yaml(certs, "    handshake_timeout_ms: 1000\n") +
        "console:\n"
        "  listen: \"127.0.0.1:0\"\n" +
        one_servo_yaml(pty);
    const std::string path = dir.file("four_doors.yaml");
    std::ofstream(path) << yaml;
    process_ = std::make_unique<ChildProcess>(
        std::vector<std::string>{bin("sms-gateway"), "--config", path, "--metrics", "127.0.0.1:0"});
    ports_[Way::Metrics] = port_after("/healthz on http://127.0.0.1:");
    ports_[Way::Plain] = port_after("modbus tcp: listening on 127.0.0.1:");
    ports_[Way::Tls] = port_after("modbus tcp security: listening on 127.0.0.1:");
    ports_[Way::Console] = port_after("console: serving the browser console on http://127.0.0.1:");
    if (!process_->wait_for_line("servos online", 15s)) {
      throw std::runtime_error("sms-gateway did not report its bus:\n" + process_->output());
    }
  }

  std::uint16_t port(Way way) const { return ports_.at(way); }
  std::string output() const { return process_->output(); }

  // A real client of that way in, once: true when it was served.
  bool served(Way way) const {
    try {
      switch (way) {
        case Way::Plain: {
          LoopbackClient client(port(way));
          // FC04 of the gateway unit: input register 5, the number of buses (answered from memory).
          client.send({0x00, 0x07, 0x00, 0x00, 0x00, 0x06, 0xFF, 0x04, 0x00, 0x05, 0x00, 0x01});
          return client.receive(11) == ByteVector{0x00, 0x07, 0x00, 0x00, 0x00, 0x05, 0xFF, 0x04, 0x02, 0x00, 0x01};
        }
        case Way::Tls: {
          TlsClient client(certs_, "read", port(way));
          return client.request({0x04, 0x00, 0x05, 0x00, 0x01}, 255) == Pdu{0x04, 0x02, 0x00, 0x01};
        }
        case Way::Console: return http_request(port(way), "GET", "/").status == 200;
        case Way::Metrics: return http_request(port(way), "GET", "/healthz").status == 200;
      }
    } catch (const std::exception&) {
      return false;  // closed before it was answered
    }
    return false;
  }

  // How long a client takes to be served; nullopt when it was not. A client that loses its
  // connection before its first request was through connects once more, as a PLC or a browser
  // does: on a loaded machine its first bytes can come after enough newer connections made it
  // the oldest waiting one.
  std::optional<std::chrono::milliseconds> time_to_serve(Way way) const {
    const auto start = std::chrono::steady_clock::now();
    for (int attempt = 0; attempt < 2; ++attempt) {
      if (served(way)) {
        return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start);
      }
    }
    return std::nullopt;
  }

  // sms_gateway_listener_closed_total of the way in, for `reason`.
  std::uint64_t closed(Way way, const std::string& reason) const {
    return sample("sms_gateway_listener_closed_total{listener=\"" + listener_label(way) + "\",reason=\"" + reason +
                  "\"} ");
  }
  // The connections of the way in that wait at its door (open, not trusted yet).
  std::uint64_t waiting(Way way) const {
    return sample("sms_gateway_listener_connections{listener=\"" + listener_label(way) + "\",state=\"waiting\"} ");
  }

 private:
  std::uint16_t port_after(const std::string& marker) {
    const auto line = process_->wait_for_line(marker, 15s);
    if (!line) throw std::runtime_error("sms-gateway did not log `" + marker + "`:\n" + process_->output());
    return static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
  }

  // The value of one sample of /metrics, named with its labels and the space after them.
  std::uint64_t sample(const std::string& name) const {
    const std::string body = http_request(port(Way::Metrics), "GET", "/metrics").body;
    const auto at = body.find(name);
    if (at == std::string::npos) throw std::runtime_error("no sample " + name + " in /metrics:\n" + body);
    return std::stoull(body.substr(at + name.size()));
  }

  std::string certs_;
  std::unique_ptr<ChildProcess> process_;
  std::map<Way, std::uint16_t> ports_;
};

class FrontDoor : public testing::TestWithParam<Way> {
 protected:
  // One gateway for the suite, started by its first test (a failure to start fails that test,
  // where a failing SetUpTestSuite would only skip them all).
  void SetUp() override {
    if (gateway_ != nullptr) return;
    dir_ = new TempDir();
    const std::string certs = dir_->file("certs");
    const std::string command = std::string(SMS_SOURCE_DIR) + "/tests/e2e/make_test_certs.sh " + certs;
    ASSERT_EQ(std::system(command.c_str()), 0) << command;
    sim_ = new SimProcess(*dir_, "sim", std::vector<std::string>{"--servo", "1:sts"});
    gateway_ = new FourDoors(*dir_, certs, sim_->pty());
  }
  static void TearDownTestSuite() {
    delete gateway_;
    delete sim_;
    delete dir_;
    gateway_ = nullptr;
    sim_ = nullptr;
    dir_ = nullptr;
  }

  // While `flood` runs, `tries` clients of this way in are each served within the bound, and the
  // door closed some of the flood's connections (`reason`) to make that so.
  void expect_served_despite(const Flood& flood, const std::string& what, const std::string& reason = "evicted") {
    const Way way = GetParam();
    const std::uint64_t closed_before = gateway_->closed(way, reason);
    std::this_thread::sleep_for(300ms);  // the flood is established
    std::chrono::milliseconds slowest{0};
    constexpr int kTries = 8;
    for (int i = 0; i < kTries; ++i) {
      const auto served = gateway_->time_to_serve(way);
      ASSERT_TRUE(served) << what << ": try " << i << " not served\n" << gateway_->output();
      EXPECT_LT(*served, kServedWithin) << what << ": try " << i;
      slowest = std::max(slowest, *served);
    }
    std::cout << listener_label(way) << ", " << what << ": " << kTries << " of " << kTries << " served, slowest "
              << slowest.count() << " ms; the flood re-opened " << flood.reopened() << " connections meanwhile\n";
    EXPECT_GT(flood.reopened(), 0u) << "the gateway closed none of the flood's connections";
    EXPECT_GT(gateway_->closed(way, reason), closed_before) << "not counted as " << reason;
  }

  std::string bytes(Attack attack) const { return attack_bytes(GetParam(), attack); }

  static TempDir* dir_;
  static SimProcess* sim_;
  static FourDoors* gateway_;
};

TempDir* FrontDoor::dir_ = nullptr;
SimProcess* FrontDoor::sim_ = nullptr;
FourDoors* FrontDoor::gateway_ = nullptr;

TEST_P(FrontDoor, SilentConnectionsFromManyAddressesKeepNobodyOut) {
  Flood flood(gateway_->port(GetParam()), addresses(2, 9), 40, bytes(Attack::Silent));
  expect_served_despite(flood, "40 silent connections from 8 addresses");
}

TEST_P(FrontDoor, SilentConnectionsFromTheClientsOwnAddressKeepItNotOut) {
  Flood flood(gateway_->port(GetParam()), {"127.0.0.1"}, 40, bytes(Attack::Silent));
  expect_served_despite(flood, "40 silent connections from the client's address");
}

TEST_P(FrontDoor, HalfSentFirstMessagesFromManyAddressesKeepNobodyOut) {
  // A flood that speaks makes room from its own addresses: those holding the most waiting
  // connections. (From the client's own address nothing tells the client from the flood; that
  // address's budget is what keeps the flood from the others.)
  Flood flood(gateway_->port(GetParam()), addresses(2, 9), 40, bytes(Attack::Partial));
  expect_served_despite(flood, "40 half-sent first messages from 8 addresses");
}

TEST_P(FrontDoor, WholeFirstMessagesThatGoNoFurtherKeepNobodyOut) {
  // A TLS ClientHello, an MBAP header, HTTP headers announcing a body: each complete, nothing
  // after. /metrics takes no request body: it answers such a POST 413 and closes it at once, so
  // nothing waits there to be evicted; it must still serve every scraper.
  const Way way = GetParam();
  Flood flood(gateway_->port(way), addresses(2, 9), 40, bytes(Attack::FullHello));
  if (way != Way::Metrics) {
    expect_served_despite(flood, "40 whole first messages going no further, from 8 addresses");
  } else {
    std::this_thread::sleep_for(300ms);
    for (int i = 0; i < 8; ++i) ASSERT_TRUE(gateway_->time_to_serve(way)) << "try " << i << "\n" << gateway_->output();
    EXPECT_GT(flood.reopened(), 0u);
  }
}

TEST_P(FrontDoor, TwoHundredSilentConnectionsFromTwentyAddressesKeepNobodyOut) {
  Flood flood(gateway_->port(GetParam()), addresses(10, 29), 200, bytes(Attack::Silent));
  expect_served_despite(flood, "200 silent connections from 20 addresses");
}

TEST_P(FrontDoor, AConnectionWithoutACompleteFirstRequestIsClosedAtTheDeadline) {
  const Way way = GetParam();
  // Plain and TLS are configured to 1 s here; the console's and /metrics' deadline is 5 s.
  const auto deadline = way == Way::Plain || way == Way::Tls ? 1s : 5s;
  const std::uint64_t before = gateway_->closed(way, "deadline");
  HttpConnection half(gateway_->port(way));  // any bytes will do: it is the listener that decides
  const std::string partial = bytes(Attack::Partial);
  half.send(partial);
  const auto start = std::chrono::steady_clock::now();
  EXPECT_TRUE(half.closed_by_peer(deadline + 10s)) << gateway_->output();
  EXPECT_GE(std::chrono::steady_clock::now() - start, deadline - 200ms);
  EXPECT_TRUE(eventually([&] { return gateway_->closed(way, "deadline") > before; }, "the deadline counted"));
  EXPECT_TRUE(gateway_->served(way));
}

INSTANTIATE_TEST_SUITE_P(EveryListener, FrontDoor, testing::Values(Way::Plain, Way::Tls, Way::Console, Way::Metrics),
                         [](const testing::TestParamInfo<Way>& info) { return listener_label(info.param); });

// A browser opens up to 6 connections to one host while it loads a page, and on the console they
// all wait at the door until a request of theirs carries a signed-in user (the login page is
// loaded before anyone signs in). None of them may be the one that makes room: a page load must
// never evict its own connections. The other doors' clients are PLCs, panels and scrapers, one
// connection each; their budgets are their own (docs/OPERATIONS.md).
class BrowserAtTheConsole : public FrontDoor {};

TEST_P(BrowserAtTheConsole, TheSixConnectionsOfAPageLoadAreAllServed) {
  const Way way = GetParam();
  ASSERT_TRUE(eventually([&] { return gateway_->waiting(way) == 0; }, "no connection waiting at the door"));
  const std::uint64_t evicted_before = gateway_->closed(way, "evicted");
  std::vector<std::unique_ptr<HttpConnection>> page_load;
  for (int i = 0; i < 6; ++i) page_load.push_back(std::make_unique<HttpConnection>(gateway_->port(way)));
  // All six admitted before any request: the door holds them at once, as a slow page load does.
  ASSERT_TRUE(eventually([&] { return gateway_->waiting(way) == 6; }, "six connections waiting at the door"))
      << gateway_->waiting(way) << " waiting, " << gateway_->closed(way, "evicted") - evicted_before << " evicted";
  for (auto& connection : page_load) connection->send("GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
  for (std::size_t i = 0; i < page_load.size(); ++i) {
    const auto response = page_load[i]->read_response();
    ASSERT_TRUE(response) << "connection " << i << " of the page load was not answered\n" << gateway_->output();
    EXPECT_EQ(response->status, 200) << "connection " << i;
  }
  EXPECT_EQ(gateway_->closed(way, "evicted"), evicted_before);
}

INSTANTIATE_TEST_SUITE_P(Console, BrowserAtTheConsole, testing::Values(Way::Console),
                         [](const testing::TestParamInfo<Way>& info) { return listener_label(info.param); });

}  // namespace
}  // namespace sms::e2e
