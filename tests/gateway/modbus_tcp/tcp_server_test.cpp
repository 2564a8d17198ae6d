// The Modbus TCP server over real loopback sockets: MBAP framing, transaction ids, pipelining,
// connection limit, idle timeout, clients vanishing mid-request, graceful shutdown. The
// handler here answers from a script (the router is tested elsewhere); answers that model bus
// work arrive later from a timer, as bus completions do.
#include "gateway/modbus_tcp/tcp_server.h"

#include <gtest/gtest.h>

#include <atomic>
#include <future>
#include <mutex>
#include <thread>

#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "tests/support/eventually.h"
#include "tests/support/loopback_client.h"

namespace sms::gateway {
namespace {

namespace asio = boost::asio;
using test::ByteVector;
using test::eventually;
using test::LoopbackClient;
using namespace std::chrono_literals;

// Answers FC03 with `count` registers holding address, address+1, ...; takes `delay_of(address)`
// to answer (0: synchronously, inside handle()).
class ScriptedHandler : public RequestHandler {
 public:
  explicit ScriptedHandler(asio::io_context& io) : io_(io) {}

  std::function<std::chrono::milliseconds(std::uint16_t address)> delay_of = [](std::uint16_t) { return 0ms; };

  void handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) override {
    const std::uint16_t address = static_cast<std::uint16_t>((pdu[1] << 8) | pdu[2]);
    const std::uint16_t count = static_cast<std::uint16_t>((pdu[3] << 8) | pdu[4]);
    {
      std::lock_guard lock(mutex_);
      started_.push_back({unit_id, address});
    }
    const int now_in_flight = ++in_flight_;
    max_in_flight_ = std::max(max_in_flight_.load(), now_in_flight);
    Bytes answer{pdu[0], static_cast<std::uint8_t>(2 * count)};
    for (std::uint16_t i = 0; i < count; ++i) {
      const std::uint16_t value = static_cast<std::uint16_t>(address + i);
      answer.push_back(static_cast<std::uint8_t>(value >> 8));
      answer.push_back(static_cast<std::uint8_t>(value & 0xFF));
    }
    const auto delay = delay_of(address);
    if (delay == 0ms) {
      finish(address, std::move(answer), reply);
      return;
    }
    auto timer = std::make_shared<asio::steady_timer>(io_, delay);
    timer->async_wait([this, timer, address, answer = std::move(answer),
                       reply](const boost::system::error_code&) mutable { finish(address, std::move(answer), reply); });
  }

  std::vector<std::pair<std::uint8_t, std::uint16_t>> started() {
    std::lock_guard lock(mutex_);
    return started_;
  }
  std::vector<std::uint16_t> completed() {
    std::lock_guard lock(mutex_);
    return completed_;
  }
  int max_in_flight() const { return max_in_flight_; }

 private:
  void finish(std::uint16_t address, Bytes answer, const Reply& reply) {
    {
      std::lock_guard lock(mutex_);
      completed_.push_back(address);  // the "bus work" is done whether or not anyone listens
    }
    --in_flight_;
    reply.send(std::move(answer));
  }

  asio::io_context& io_;
  std::mutex mutex_;
  std::vector<std::pair<std::uint8_t, std::uint16_t>> started_;
  std::vector<std::uint16_t> completed_;
  std::atomic<int> in_flight_{0};
  std::atomic<int> max_in_flight_{0};
};

class TcpServerTest : public ::testing::Test {
 protected:
  void start(TcpServerOptions options = {}) {
    options.host = "127.0.0.1";
    options.port = 0;
    server_ = std::make_unique<TcpServer>(io_, options, handler_);
    server_->start();
    thread_ = std::thread([this] { io_.run(); });
  }

  // Runs `f` on the io thread and waits for it.
  template <typename F>
  auto on_io(F f) {
    std::promise<decltype(f())> done;
    asio::post(io_, [&] {
      if constexpr (std::is_void_v<decltype(f())>) {
        f();
        done.set_value();
      } else {
        done.set_value(f());
      }
    });
    return done.get_future().get();
  }

  void TearDown() override {
    if (thread_.joinable()) {
      on_io([this] { server_->close_all(); });
      work_.reset();
      io_.stop();
      thread_.join();
    }
    server_.reset();
  }

  std::uint16_t port() const { return server_->port(); }

  asio::io_context io_;
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work_{io_.get_executor()};
  ScriptedHandler handler_{io_};
  std::unique_ptr<TcpServer> server_;
  std::thread thread_;
};

// FC03 request: transaction `tid`, unit `unit`, `count` registers from `address`.
ByteVector read_request(std::uint16_t tid, std::uint8_t unit, std::uint16_t address, std::uint16_t count) {
  return {static_cast<std::uint8_t>(tid >> 8),
          static_cast<std::uint8_t>(tid),
          0x00,
          0x00,
          0x00,
          0x06,
          unit,
          0x03,
          static_cast<std::uint8_t>(address >> 8),
          static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(count >> 8),
          static_cast<std::uint8_t>(count)};
}

// The answer ScriptedHandler gives to a one-register read at `address`.
ByteVector one_register_answer(std::uint16_t tid, std::uint8_t unit, std::uint16_t address) {
  return {static_cast<std::uint8_t>(tid >> 8),
          static_cast<std::uint8_t>(tid),
          0x00,
          0x00,
          0x00,
          0x05,
          unit,
          0x03,
          0x02,
          static_cast<std::uint8_t>(address >> 8),
          static_cast<std::uint8_t>(address)};
}

TEST_F(TcpServerTest, AnswersWithTheTransactionIdAndUnitEchoed) {
  start();
  LoopbackClient client(port());
  client.send({0xBE, 0xEF, 0x00, 0x00, 0x00, 0x06, 0x07, 0x03, 0x00, 0x38, 0x00, 0x02});
  EXPECT_EQ(client.receive(13),
            (ByteVector{0xBE, 0xEF, 0x00, 0x00, 0x00, 0x07, 0x07, 0x03, 0x04, 0x00, 0x38, 0x00, 0x39}));
}

TEST_F(TcpServerTest, RequestTricklingInByteByByteIsAnsweredOnce) {
  start();
  LoopbackClient client(port());
  const ByteVector request = read_request(0x0102, 1, 0x0010, 1);
  for (const std::uint8_t byte : request) {
    client.send({byte});
    std::this_thread::sleep_for(2ms);
  }
  EXPECT_EQ(client.receive(11), one_register_answer(0x0102, 1, 0x0010));
  EXPECT_EQ(client.receive(1, 100ms), ByteVector{});
}

TEST_F(TcpServerTest, PipelinedRequestsAreAnsweredInOrderEvenWhenEarlierOnesTakeLonger) {
  handler_.delay_of = [](std::uint16_t address) { return std::chrono::milliseconds(40 - 10 * address); };
  start();
  LoopbackClient client(port());
  ByteVector burst;
  for (std::uint16_t i = 0; i < 4; ++i) {
    const ByteVector request = read_request(static_cast<std::uint16_t>(100 + i), 9, i, 1);
    burst.insert(burst.end(), request.begin(), request.end());
  }
  client.send(burst);  // one TCP write: four requests back to back

  ByteVector expected;
  for (std::uint16_t i = 0; i < 4; ++i) {
    const ByteVector answer = one_register_answer(static_cast<std::uint16_t>(100 + i), 9, i);
    expected.insert(expected.end(), answer.begin(), answer.end());
  }
  EXPECT_EQ(client.receive(expected.size()), expected);
  // One at a time per connection: the handler never saw two of them at once.
  EXPECT_EQ(handler_.max_in_flight(), 1);
  EXPECT_EQ(handler_.completed(), (std::vector<std::uint16_t>{0, 1, 2, 3}));
}

TEST_F(TcpServerTest, LongPipelinePastTheReadPauseIsAnsweredCompletelyInOrder) {
  TcpServerOptions options;
  options.max_pipelined = 4;  // the session stops reading after 4 waiting requests
  start(options);
  LoopbackClient client(port());
  ByteVector burst;
  ByteVector expected;
  for (std::uint16_t i = 0; i < 200; ++i) {
    const ByteVector request = read_request(i, 1, i, 1);
    burst.insert(burst.end(), request.begin(), request.end());
    const ByteVector answer = one_register_answer(i, 1, i);
    expected.insert(expected.end(), answer.begin(), answer.end());
  }
  client.send(burst);
  EXPECT_EQ(client.receive(expected.size()), expected);
}

TEST_F(TcpServerTest, ConnectionsAreServedConcurrently) {
  // Connection A's request takes 300 ms; B's answer must not wait for it.
  handler_.delay_of = [](std::uint16_t address) { return address == 1 ? 300ms : 0ms; };
  start();
  LoopbackClient a(port());
  LoopbackClient b(port());
  a.send(read_request(1, 1, 1, 1));
  std::this_thread::sleep_for(20ms);
  const auto before = std::chrono::steady_clock::now();
  b.send(read_request(2, 1, 2, 1));
  EXPECT_EQ(b.receive(11), one_register_answer(2, 1, 2));
  EXPECT_LT(std::chrono::steady_clock::now() - before, 200ms);
  EXPECT_EQ(a.receive(11), one_register_answer(1, 1, 1));
}

TEST_F(TcpServerTest, BadProtocolIdClosesTheConnectionAfterAnsweringWhatCameBefore) {
  start();
  LoopbackClient client(port());
  ByteVector bytes = read_request(7, 1, 5, 1);
  const ByteVector bad{0x00, 0x08, 0x00, 0x01, 0x00, 0x06, 0x01, 0x03, 0x00, 0x00, 0x00, 0x01};  // protocol id 1
  bytes.insert(bytes.end(), bad.begin(), bad.end());
  client.send(bytes);
  EXPECT_EQ(client.receive(11), one_register_answer(7, 1, 5));
  EXPECT_TRUE(client.closed_by_peer());
  EXPECT_EQ(server_->stats().bad_headers, 1u);
}

TEST_F(TcpServerTest, LengthFieldBeyondTheMaximumClosesTheConnection) {
  start();
  LoopbackClient client(port());
  client.send({0x00, 0x01, 0x00, 0x00, 0x01, 0x00, 0x01, 0x03});  // length 256 > 254
  EXPECT_TRUE(client.closed_by_peer());
}

TEST_F(TcpServerTest, ConnectionsOverTheLimitAreAcceptedAndClosedAtOnce) {
  TcpServerOptions options;
  options.max_connections = 2;
  start(options);
  LoopbackClient first(port());
  LoopbackClient second(port());
  first.send(read_request(1, 1, 1, 1));  // both admitted: they answer
  second.send(read_request(2, 1, 2, 1));
  ASSERT_EQ(first.receive(11), one_register_answer(1, 1, 1));
  ASSERT_EQ(second.receive(11), one_register_answer(2, 1, 2));

  LoopbackClient third(port());
  EXPECT_TRUE(third.closed_by_peer());
  LoopbackClient fourth(port());
  EXPECT_TRUE(fourth.closed_by_peer());
  EXPECT_EQ(server_->stats().refused, 2u);
  EXPECT_EQ(server_->stats().refusals[0].max_connections, 2u);  // counted for the plain listener
  EXPECT_EQ(server_->stats().refusals[1].max_connections, 0u);

  first.close();  // a slot frees up: a new client is served again
  ASSERT_TRUE(eventually([&] { return server_->stats().open_connections == 1; }, "the closed connection's slot freed"));
  LoopbackClient fifth(port());
  fifth.send(read_request(5, 1, 5, 1));
  EXPECT_EQ(fifth.receive(11), one_register_answer(5, 1, 5));
}

config::IpNetwork network(const char* text) {
  auto parsed = config::parse_ip_network(text);
  if (!parsed) throw std::invalid_argument(parsed.error());
  return *parsed;
}

TEST_F(TcpServerTest, ClientNotInTheAllowListIsClosedWithoutAnAnswerAndCounted) {
  TcpServerOptions options;
  options.allow = {network("192.168.10.0/24"), network("fd00::/8")};
  start(options);
  LoopbackClient outsider(port());
  outsider.send(read_request(1, 1, 1, 1));
  EXPECT_TRUE(outsider.closed_by_peer());
  EXPECT_TRUE(handler_.started().empty());  // the request never reached the handler
  EXPECT_EQ(server_->stats().denied, 1u);
  EXPECT_EQ(server_->stats().refusals[0].allow, 1u);
  EXPECT_EQ(server_->stats().accepted, 0u);
}

TEST_F(TcpServerTest, ClientInTheAllowListIsServed) {
  TcpServerOptions options;
  options.allow = {network("192.168.10.0/24"), network("127.0.0.1")};
  start(options);
  LoopbackClient insider(port());
  insider.send(read_request(1, 1, 7, 1));
  EXPECT_EQ(insider.receive(11), one_register_answer(1, 1, 7));
  EXPECT_EQ(server_->stats().denied, 0u);
}

TEST_F(TcpServerTest, IdleConnectionIsClosedAfterTheTimeout) {
  TcpServerOptions options;
  options.idle_timeout = 150ms;
  start(options);
  LoopbackClient client(port());
  client.send(read_request(1, 1, 1, 1));
  ASSERT_EQ(client.receive(11), one_register_answer(1, 1, 1));
  const auto answered = std::chrono::steady_clock::now();
  EXPECT_TRUE(client.closed_by_peer(2s));
  const auto waited = std::chrono::steady_clock::now() - answered;
  EXPECT_GE(waited, 120ms);
  EXPECT_LT(waited, 1s);
  EXPECT_EQ(server_->stats().idle_closed, 1u);
}

// A client that pipelines reads and never takes its answers: the server stops starting its
// requests once 64 KiB of answers wait, and closes it when a write makes no progress for the
// idle timeout. Others are served meanwhile.
TEST_F(TcpServerTest, ClientThatTakesNoAnswersIsHeldBackThenClosedAfterTheIdleTimeout) {
  TcpServerOptions options;
  options.idle_timeout = 300ms;
  start(options);
  const int hoarder = ::socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(hoarder, 0);
  const int small = 4096;  // a small receive window: the answers back up quickly
  ::setsockopt(hoarder, SOL_SOCKET, SO_RCVBUF, &small, sizeof small);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(port());
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::connect(hoarder, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  // Up to 40 000 reads of 125 registers (10 MB of answers), sent for as long as the server takes them.
  ByteVector burst;
  for (std::uint16_t i = 0; i < 40000; ++i) {
    const auto request = read_request(i, 1, 0, 125);
    burst.insert(burst.end(), request.begin(), request.end());
  }
  std::size_t sent = 0;
  const auto give_up = std::chrono::steady_clock::now() + 3s;
  while (sent < burst.size() && std::chrono::steady_clock::now() < give_up) {
    const ssize_t n = ::send(hoarder, burst.data() + sent, burst.size() - sent, MSG_DONTWAIT | MSG_NOSIGNAL);
    if (n > 0) {
      sent += static_cast<std::size_t>(n);
    } else {
      std::this_thread::sleep_for(10ms);
    }
  }
  // Held back: far from every request was started.
  EXPECT_LT(handler_.started().size(), 40000u);

  LoopbackClient other(port());
  other.send(read_request(7, 1, 3, 1));
  EXPECT_EQ(other.receive(11), one_register_answer(7, 1, 3));
  other.close();

  EXPECT_TRUE(eventually(
      [&] {
        const auto stats = server_->stats();
        return stats.open_connections == 0 && stats.idle_closed == 1;
      },
      "the client taking no answers closed"));
  ::close(hoarder);
}

TEST_F(TcpServerTest, RequestTakingLongerThanTheIdleTimeoutIsStillAnswered) {
  handler_.delay_of = [](std::uint16_t) { return 400ms; };
  TcpServerOptions options;
  options.idle_timeout = 100ms;
  start(options);
  LoopbackClient client(port());
  client.send(read_request(3, 1, 3, 1));
  EXPECT_EQ(client.receive(11, 2s), one_register_answer(3, 1, 3));
}

TEST_F(TcpServerTest, ClientLeavingMidRequestLetsTheWorkFinishAndTheServerCarriesOn) {
  handler_.delay_of = [](std::uint16_t address) { return address == 42 ? 150ms : 0ms; };
  start();
  {
    LoopbackClient leaving(port());
    leaving.send(read_request(1, 1, 42, 1));
    ASSERT_TRUE(eventually([&] { return !handler_.started().empty(); }, "the request started"));
  }  // closes with the request still being answered
  ASSERT_TRUE(eventually([&] { return !handler_.completed().empty(); }, "the request completed"));
  EXPECT_EQ(handler_.completed(), (std::vector<std::uint16_t>{42}));
  LoopbackClient next(port());
  next.send(read_request(2, 1, 2, 1));
  EXPECT_EQ(next.receive(11), one_register_answer(2, 1, 2));
  EXPECT_EQ(server_->stats().open_connections, 1u);
}

TEST_F(TcpServerTest, ShutdownAnswersTheRequestInFlightThenClosesAndDropsTheQueuedOnes) {
  handler_.delay_of = [](std::uint16_t address) { return address == 1 ? 200ms : 0ms; };
  start();
  LoopbackClient client(port());
  ByteVector two = read_request(1, 1, 1, 1);
  const ByteVector queued = read_request(2, 1, 2, 1);
  two.insert(two.end(), queued.begin(), queued.end());
  client.send(two);
  ASSERT_TRUE(eventually([&] { return !handler_.started().empty(); }, "the first request started"));

  std::promise<void> all_closed;
  on_io([&] { server_->shutdown([&] { all_closed.set_value(); }); });
  EXPECT_EQ(client.receive(11), one_register_answer(1, 1, 1));
  EXPECT_TRUE(client.closed_by_peer());
  EXPECT_EQ(all_closed.get_future().wait_for(2s), std::future_status::ready);
  EXPECT_EQ(handler_.started().size(), 1u);                       // the queued request never started
  EXPECT_THROW(LoopbackClient late(port()), std::runtime_error);  // not listening any more
}

TEST_F(TcpServerTest, ShutdownWithNoConnectionsCompletesAtOnce) {
  start();
  std::promise<void> all_closed;
  on_io([&] { server_->shutdown([&] { all_closed.set_value(); }); });
  EXPECT_EQ(all_closed.get_future().wait_for(1s), std::future_status::ready);
}

TEST_F(TcpServerTest, PortInUseNamesTheAddressAndWhatToDo) {
  start();
  TcpServerOptions options;
  options.host = "127.0.0.1";
  options.port = port();
  asio::io_context other_io;
  TcpServer second(other_io, options, handler_);
  try {
    second.start();
    FAIL() << "a second server bound a port in use";
  } catch (const std::runtime_error& error) {
    const std::string message = error.what();
    EXPECT_NE(message.find("127.0.0.1:" + std::to_string(port())), std::string::npos) << message;
    EXPECT_NE(message.find("--listen"), std::string::npos) << message;
  }
}

TEST_F(TcpServerTest, UnresolvableHostIsAClearError) {
  TcpServerOptions options;
  options.host = "no-such-host.invalid";
  options.port = 0;
  TcpServer server(io_, options, handler_);
  try {
    server.start();
    FAIL() << "bound an unresolvable host";
  } catch (const std::runtime_error& error) {
    EXPECT_NE(std::string(error.what()).find("no-such-host.invalid"), std::string::npos) << error.what();
  }
}

}  // namespace
}  // namespace sms::gateway
