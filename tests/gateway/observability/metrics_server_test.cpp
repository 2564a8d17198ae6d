// The metrics HTTP endpoint over real loopback sockets: /metrics and /healthz, other paths and
// methods, HEAD, keep-alive, size limits, slow clients, the connection limit, start and stop.
// The snapshot comes from real counter objects the test fills and changes.
#include <gtest/gtest.h>

#include <sstream>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include "gateway/observability/metrics_server.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"

// Designated initializers leave the members a test does not name at their defaults, on purpose.
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using test::http_request;
using test::HttpConnection;
using test::parse_exposition;

// One bus "arm" whose state and frame counter the test sets.
class MetricsServerTest : public ::testing::Test {
 protected:
  void start(MetricsServerOptions options = {}) {
    options.listen = {"127.0.0.1", 0};
    server_ = std::make_unique<MetricsServer>(std::move(options), [this] { return snapshot(); });
    server_->start();
    ASSERT_NE(server_->port(), 0);
  }

  MetricsSnapshot snapshot() {
    ++snapshots_;
    MetricsSnapshot snapshot;
    snapshot.version = "9.8.7";
    BusMetrics bus;
    bus.name = "arm";
    bus.protocol = "feetech";
    bus.up = bus_up_.load();
    bus.counters = counters_.snapshot();
    snapshot.buses.push_back(bus);
    snapshot.traffic = traffic_.snapshot();
    return snapshot;
  }

  std::uint16_t port() const { return server_->port(); }

  std::unique_ptr<MetricsServer> server_;
  BusCounters counters_;
  ModbusTrafficCounters traffic_;
  std::atomic<bool> bus_up_{true};
  std::atomic<int> snapshots_{0};
};

constexpr char kGetMetrics[] = "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";

TEST_F(MetricsServerTest, MetricsAreServedAsPrometheusTextAndAreLive) {
  start();
  counters_.frames_ok = 41;
  const auto first = http_request(port(), "GET", "/metrics");
  EXPECT_EQ(first.status, 200);
  EXPECT_EQ(first.header("content-type"), "text/plain; version=0.0.4; charset=utf-8");
  EXPECT_EQ(first.header("content-length"), std::to_string(first.body.size()));
  const auto exposition = parse_exposition(first.body);
  EXPECT_TRUE(exposition.errors.empty()) << ::testing::PrintToString(exposition.errors);
  EXPECT_EQ(exposition.value("sms_gateway_bus_frames_ok_total{bus=\"arm\",protocol=\"feetech\"}"), "41");
  EXPECT_EQ(exposition.value("sms_gateway_build_info{version=\"9.8.7\"}"), "1");

  counters_.frames_ok += 1;
  traffic_.count_request(std::vector<std::uint8_t>{0x03, 0x00, 0x00, 0x00, 0x01});
  const auto second = parse_exposition(http_request(port(), "GET", "/metrics").body);
  EXPECT_EQ(second.value("sms_gateway_bus_frames_ok_total{bus=\"arm\",protocol=\"feetech\"}"), "42");
  EXPECT_EQ(second.value("sms_gateway_modbus_requests_total{function=\"3\",name=\"read_holding_registers\"}"), "1");
}

TEST_F(MetricsServerTest, QueryStringIsIgnored) {
  start();
  counters_.frames_ok = 7;
  const auto plain = http_request(port(), "GET", "/metrics");
  const auto queried = http_request(port(), "GET", "/metrics?name[]=up");
  // The whole metrics text, exactly as without a query: no filter, no empty or error page (the
  // endpoint's own connection counts moved on between the two).
  EXPECT_EQ(queried.status, 200);
  EXPECT_EQ(queried.header("content-type"), "text/plain; version=0.0.4; charset=utf-8");
  const auto without_listener_counts = [](const std::string& text) {
    std::string kept;
    std::istringstream lines(text);
    for (std::string line; std::getline(lines, line);) {
      if (!line.starts_with("sms_gateway_listener_")) kept += line + "\n";
    }
    return kept;
  };
  EXPECT_EQ(without_listener_counts(queried.body), without_listener_counts(plain.body));
  const auto exposition = parse_exposition(queried.body);
  EXPECT_TRUE(exposition.errors.empty()) << ::testing::PrintToString(exposition.errors);
  EXPECT_EQ(exposition.value("sms_gateway_bus_frames_ok_total{bus=\"arm\",protocol=\"feetech\"}"), "7");
  EXPECT_EQ(exposition.value("sms_gateway_build_info{version=\"9.8.7\"}"), "1");
  EXPECT_EQ(snapshots_.load(), 2);  // each request rendered the gateway's state
}

TEST_F(MetricsServerTest, HealthzIsOkWhileEveryBusIsUpAnd503NamingTheBusOtherwise) {
  start();
  const auto up = http_request(port(), "GET", "/healthz");
  EXPECT_EQ(up.status, 200);
  EXPECT_EQ(up.body, "ok\n");
  EXPECT_EQ(up.header("content-type"), "text/plain; charset=utf-8");

  bus_up_ = false;
  const auto down = http_request(port(), "GET", "/healthz");
  EXPECT_EQ(down.status, 503);
  EXPECT_EQ(down.body, "bus arm is down\n");

  bus_up_ = true;
  EXPECT_EQ(http_request(port(), "GET", "/healthz").status, 200);
}

TEST_F(MetricsServerTest, OtherPathsAre404AndOtherMethods405) {
  start();
  const auto missing = http_request(port(), "GET", "/");
  EXPECT_EQ(missing.status, 404);
  EXPECT_EQ(missing.body, "not found; try /metrics or /healthz\n");
  EXPECT_EQ(http_request(port(), "GET", "/metrics/extra").status, 404);
  EXPECT_EQ(http_request(port(), "GET", "/METRICS").status, 404);

  const auto post = http_request(port(), "POST", "/metrics");
  EXPECT_EQ(post.status, 405);
  EXPECT_EQ(post.header("allow"), "GET, HEAD");
  EXPECT_EQ(http_request(port(), "DELETE", "/healthz").status, 405);
  EXPECT_EQ(snapshots_.load(), 0);  // none of these looked at the gateway
}

TEST_F(MetricsServerTest, HeadAnswersHeadersWithoutABody) {
  start();
  const auto get = http_request(port(), "GET", "/healthz");
  HttpConnection connection(port());
  connection.send("HEAD /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n");
  const auto head = connection.read_response(true);
  ASSERT_TRUE(head);
  EXPECT_EQ(head->status, 200);
  EXPECT_EQ(head->header("content-length"), std::to_string(get.body.size()));
  EXPECT_TRUE(connection.closed_by_peer());
  EXPECT_EQ(connection.pending(), "");  // no body bytes followed the headers
}

TEST_F(MetricsServerTest, KeepAliveServesSeveralRequestsOnOneConnection) {
  start();
  HttpConnection connection(port());
  for (int i = 0; i < 3; ++i) {
    counters_.frames_ok = static_cast<std::uint64_t>(i);
    connection.send(kGetMetrics);
    const auto response = connection.read_response();
    ASSERT_TRUE(response) << "request " << i;
    EXPECT_EQ(response->status, 200);
    EXPECT_EQ(
        parse_exposition(response->body).value("sms_gateway_bus_frames_ok_total{bus=\"arm\",protocol=\"feetech\"}"),
        std::to_string(i));
  }
  // Two pipelined requests in one write: two answers, in order.
  connection.send(std::string(kGetMetrics) + "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
  const auto metrics = connection.read_response();
  const auto health = connection.read_response();
  ASSERT_TRUE(metrics && health);
  EXPECT_EQ(metrics->header("content-type"), "text/plain; version=0.0.4; charset=utf-8");
  EXPECT_EQ(health->body, "ok\n");
}

TEST_F(MetricsServerTest, Http10ClientGetsItsAnswerAndTheConnectionCloses) {
  start();
  HttpConnection connection(port());
  connection.send("GET /healthz HTTP/1.0\r\n\r\n");
  const auto response = connection.read_response();
  ASSERT_TRUE(response);
  EXPECT_EQ(response->status, 200);
  EXPECT_EQ(response->body, "ok\n");
  EXPECT_TRUE(connection.closed_by_peer());
}

TEST_F(MetricsServerTest, OversizedHeadersAre431AndTheConnectionCloses) {
  MetricsServerOptions options;
  options.max_request_bytes = 1024;
  start(options);
  HttpConnection connection(port());
  connection.send("GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Padding: " + std::string(4000, 'a') + "\r\n\r\n");
  const auto response = connection.read_response();
  ASSERT_TRUE(response);
  EXPECT_EQ(response->status, 431);
  EXPECT_TRUE(connection.closed_by_peer());
}

TEST_F(MetricsServerTest, RequestWithABodyIs413) {
  start();
  HttpConnection connection(port());
  connection.send("GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 5\r\n\r\nhello");
  const auto response = connection.read_response();
  ASSERT_TRUE(response);
  EXPECT_EQ(response->status, 413);
  EXPECT_TRUE(connection.closed_by_peer());
}

TEST_F(MetricsServerTest, GarbageIs400) {
  start();
  HttpConnection connection(port());
  connection.send("\x01\x02\x03\x04 nonsense\r\n\r\n");
  const auto response = connection.read_response();
  ASSERT_TRUE(response);
  EXPECT_EQ(response->status, 400);
  EXPECT_TRUE(connection.closed_by_peer());
}

TEST_F(MetricsServerTest, SlowClientIsClosedAtTheTimeoutWhileOthersAreServed) {
  MetricsServerOptions options;
  options.request_timeout = 300ms;
  start(options);
  HttpConnection slow(port());
  slow.send("GET /metr");  // and nothing more
  const auto started = std::chrono::steady_clock::now();
  // Meanwhile another client is answered at once.
  EXPECT_EQ(http_request(port(), "GET", "/healthz").status, 200);
  EXPECT_LT(std::chrono::steady_clock::now() - started, 250ms);
  EXPECT_TRUE(slow.closed_by_peer(3s));
  const auto waited = std::chrono::steady_clock::now() - started;
  EXPECT_GE(waited, 250ms);
  EXPECT_LT(waited, 2s);
}

TEST_F(MetricsServerTest, IdleKeepAliveConnectionIsClosedAtTheTimeout) {
  MetricsServerOptions options;
  options.request_timeout = 200ms;
  start(options);
  HttpConnection connection(port());
  connection.send(kGetMetrics);
  ASSERT_TRUE(connection.read_response());
  EXPECT_TRUE(connection.closed_by_peer(2s));
}

TEST_F(MetricsServerTest, ConnectionsOverTheLimitAreClosedAtOnce) {
  MetricsServerOptions options;
  options.door.max_served = 2;
  start(options);
  auto first = std::make_unique<HttpConnection>(port());
  HttpConnection second(port());
  // Both are being served (answered) before the third arrives.
  first->send(kGetMetrics);
  second.send(kGetMetrics);
  ASSERT_TRUE(first->read_response());
  ASSERT_TRUE(second.read_response());

  HttpConnection third(port());
  EXPECT_TRUE(third.closed_by_peer(2s));

  first.reset();  // a place frees up
  std::optional<test::HttpResponse> answer;
  ASSERT_TRUE(test::eventually(
      [&] {  // until the server has seen the first one go
        HttpConnection fourth(port());
        fourth.send(kGetMetrics);
        answer = fourth.read_response(false, 500ms);
        return answer.has_value();
      },
      "a new connection served once the first one left"));
  EXPECT_EQ(answer->status, 200);
}

TEST_F(MetricsServerTest, SnapshotFailureIs500WithTheReason) {
  server_ = std::make_unique<MetricsServer>(MetricsServerOptions{.listen = {"127.0.0.1", 0}}, []() -> MetricsSnapshot {
    throw std::runtime_error("counters unavailable");
  });
  server_->start();
  const auto response = http_request(port(), "GET", "/metrics");
  EXPECT_EQ(response.status, 500);
  EXPECT_EQ(response.body, "counters unavailable\n");
}

TEST_F(MetricsServerTest, StopClosesOpenConnectionsAndTheListener) {
  start();
  HttpConnection connection(port());
  connection.send(kGetMetrics);
  ASSERT_TRUE(connection.read_response());
  const std::uint16_t was = port();
  server_->stop();
  EXPECT_TRUE(connection.closed_by_peer(2s));
  EXPECT_THROW(HttpConnection{was}, std::runtime_error);
  server_->stop();  // idempotent
}

TEST(MetricsServerStart, PortInUseIsReportedWithWhatToDo) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(fd, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  ASSERT_EQ(::listen(fd, 1), 0);
  socklen_t length = sizeof address;
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
  const std::uint16_t taken = ntohs(address.sin_port);

  MetricsServer server({.listen = {"127.0.0.1", taken}}, [] { return MetricsSnapshot{}; });
  try {
    server.start();
    ADD_FAILURE() << "start() should have thrown";
  } catch (const std::runtime_error& error) {
    const std::string text = error.what();
    EXPECT_NE(text.find("cannot serve metrics on 127.0.0.1:" + std::to_string(taken) + ": "), std::string::npos)
        << text;
    EXPECT_NE(text.find("choose a free port with --metrics HOST:PORT or logging.metrics_listen"), std::string::npos)
        << text;
  }
  ::close(fd);
}

TEST(MetricsServerStart, UnresolvableHostIsReported) {
  MetricsServer server({.listen = {"no-such-host.invalid", 0}}, [] { return MetricsSnapshot{}; });
  try {
    server.start();
    ADD_FAILURE() << "start() should have thrown";
  } catch (const std::runtime_error& error) {
    EXPECT_NE(
        std::string(error.what()).find("cannot serve metrics on no-such-host.invalid:0: the host does not resolve"),
        std::string::npos)
        << error.what();
  }
}

}  // namespace
}  // namespace sms::gateway
