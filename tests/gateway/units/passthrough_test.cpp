// Transparent forwarding: libmodbus TCP clients -> ForwardGateway (sms-gateway forward) -> a
// pty line -> a plain libmodbus RTU slave in a test thread (modbus_receive + modbus_reply), the
// kind of third-party device a Modbus TCP -> RTU gateway fronts.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <modbus/modbus.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "gateway/bus/rtu_master.h"
#include "gateway/units/passthrough.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using testing::eventually;

// Two ptys whose masters are joined by a relay thread: what one side writes on its slave
// arrives on the other's, like two devices on one wire. The relay can damage the next answer
// travelling from B to A.
class JoinedPtys {
 public:
  JoinedPtys() {
    for (int side = 0; side < 2; ++side) {
      masters_[side] = ::posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK);
      if (masters_[side] < 0 || ::grantpt(masters_[side]) != 0 || ::unlockpt(masters_[side]) != 0) {
        throw std::runtime_error("cannot create a pty");
      }
      paths_[side] = ::ptsname(masters_[side]);
      // Held open (raw) for the test's life: the masters never see a hang-up between the
      // libmodbus opens and closes of the slaves.
      slaves_[side] = ::open(paths_[side].c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
      termios raw{};
      ::tcgetattr(slaves_[side], &raw);
      ::cfmakeraw(&raw);
      ::tcsetattr(slaves_[side], TCSANOW, &raw);
    }
    if (::pipe(wake_) != 0) throw std::runtime_error("pipe");
    relay_ = std::thread([this] { run(); });
  }
  ~JoinedPtys() {
    stop_ = true;
    [[maybe_unused]] const auto written = ::write(wake_[1], "x", 1);
    relay_.join();
    for (int side = 0; side < 2; ++side) {
      ::close(slaves_[side]);
      ::close(masters_[side]);
    }
    ::close(wake_[0]);
    ::close(wake_[1]);
  }
  const std::string& a() const { return paths_[0]; }
  const std::string& b() const { return paths_[1]; }
  void corrupt_next_from_b() { corrupt_from_b_ = true; }

 private:
  void run() {
    std::array<std::uint8_t, 512> buffer{};
    while (!stop_) {
      std::array<pollfd, 3> fds{{{masters_[0], POLLIN, 0}, {masters_[1], POLLIN, 0}, {wake_[0], POLLIN, 0}}};
      if (::poll(fds.data(), fds.size(), 100) <= 0) continue;
      for (int side = 0; side < 2; ++side) {
        if ((fds[side].revents & POLLIN) == 0) continue;
        const ssize_t got = ::read(masters_[side], buffer.data(), buffer.size());
        if (got <= 0) continue;
        if (side == 1 && corrupt_from_b_.exchange(false)) buffer[static_cast<std::size_t>(got) - 1] ^= 0x5A;
        [[maybe_unused]] const auto written = ::write(masters_[1 - side], buffer.data(), static_cast<std::size_t>(got));
      }
    }
  }
  std::array<int, 2> masters_{-1, -1};
  std::array<int, 2> slaves_{-1, -1};
  std::array<std::string, 2> paths_;
  int wake_[2] = {-1, -1};
  std::atomic<bool> stop_{false};
  std::atomic<bool> corrupt_from_b_{false};
  std::thread relay_;
};

// A plain libmodbus RTU slave: 32 coils, 32 discrete inputs, 32 holding and 32 input registers.
class PlainRtuSlave {
 public:
  PlainRtuSlave(const std::string& device, int slave) {
    context_ = modbus_new_rtu(device.c_str(), 115'200, 'N', 8, 1);
    modbus_set_slave(context_, slave);
    if (modbus_connect(context_) != 0) throw std::runtime_error("slave: cannot open " + device);
    modbus_set_indication_timeout(context_, 0, 50'000);  // so the loop sees stop_
    mapping_ = modbus_mapping_new(32, 32, 32, 32);
    for (int i = 0; i < 32; ++i) mapping_->tab_input_registers[i] = static_cast<std::uint16_t>(100 + i);
    thread_ = std::thread([this] { run(); });
  }
  ~PlainRtuSlave() {
    stop_ = true;
    thread_.join();
    modbus_mapping_free(mapping_);
    modbus_close(context_);
    modbus_free(context_);
  }
  std::uint16_t holding(int address) {
    std::lock_guard lock(mutex_);
    return mapping_->tab_registers[address];
  }
  std::uint8_t coil(int address) {
    std::lock_guard lock(mutex_);
    return mapping_->tab_bits[address];
  }

 private:
  void run() {
    std::array<std::uint8_t, MODBUS_RTU_MAX_ADU_LENGTH> query{};
    while (!stop_) {
      const int received = modbus_receive(context_, query.data());
      if (received <= 0) continue;
      std::lock_guard lock(mutex_);
      modbus_reply(context_, query.data(), received, mapping_);
    }
  }
  modbus_t* context_ = nullptr;
  modbus_mapping_t* mapping_ = nullptr;
  std::mutex mutex_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

class TcpClient {
 public:
  TcpClient(std::uint16_t port, int unit) {
    context_ = modbus_new_tcp("127.0.0.1", port);
    modbus_set_response_timeout(context_, 3, 0);
    if (modbus_connect(context_) != 0) throw std::runtime_error("cannot connect to the forwarder");
    modbus_set_slave(context_, unit);
  }
  ~TcpClient() {
    modbus_close(context_);
    modbus_free(context_);
  }
  modbus_t* operator*() { return context_; }

 private:
  modbus_t* context_;
};

class ForwardTest : public ::testing::Test {
 protected:
  virtual BroadcastReply broadcast_reply() const { return BroadcastReply::None; }
  void SetUp() override {
    slave_ = std::make_unique<PlainRtuSlave>(line_.b(), 17);
    ForwardOptions options;
    options.broadcast_reply = broadcast_reply();
    options.serial = SerialSettings{line_.a(), 115'200};
    options.rtu.byte_timeout = 20ms;
    options.response_timeout = 50ms;
    options.retries = 2;
    options.listen = {"127.0.0.1", 0};
    forwarder_ = std::make_unique<ForwardGateway>(options);
    forwarder_->start();
    ASSERT_TRUE(eventually([&] { return forwarder_->engine().bus_up(); }));
  }
  void TearDown() override { forwarder_->stop(); }

  JoinedPtys line_;
  std::unique_ptr<PlainRtuSlave> slave_;
  std::unique_ptr<ForwardGateway> forwarder_;
};

TEST_F(ForwardTest, ForwardsReadsAndWritesToAPlainSlaveUnchanged) {
  TcpClient client(forwarder_->port(), 17);
  ASSERT_EQ(modbus_write_register(*client, 5, 1234), 1) << modbus_strerror(errno);
  EXPECT_EQ(slave_->holding(5), 1234);
  const std::uint16_t values[3] = {7, 8, 9};
  ASSERT_EQ(modbus_write_registers(*client, 10, 3, values), 3) << modbus_strerror(errno);
  std::uint16_t read[4] = {};
  ASSERT_EQ(modbus_read_registers(*client, 9, 4, read), 4) << modbus_strerror(errno);
  EXPECT_EQ(read[0], 0);
  EXPECT_EQ(read[1], 7);
  EXPECT_EQ(read[3], 9);
  ASSERT_EQ(modbus_read_input_registers(*client, 2, 2, read), 2) << modbus_strerror(errno);
  EXPECT_EQ(read[0], 102);
  EXPECT_EQ(read[1], 103);
  ASSERT_EQ(modbus_write_bit(*client, 3, 1), 1) << modbus_strerror(errno);
  EXPECT_EQ(slave_->coil(3), 1);
  std::uint8_t bits[4] = {};
  ASSERT_EQ(modbus_read_bits(*client, 2, 4, bits), 4) << modbus_strerror(errno);
  EXPECT_EQ(bits[0], 0);
  EXPECT_EQ(bits[1], 1);
  // FC23 write-and-read in one request.
  const std::uint16_t written[1] = {4321};
  ASSERT_EQ(modbus_write_and_read_registers(*client, 20, 1, written, 19, 2, read), 2) << modbus_strerror(errno);
  EXPECT_EQ(read[1], 4321);
}

TEST_F(ForwardTest, PassesTheSlavesExceptionsThrough) {
  TcpClient client(forwarder_->port(), 17);
  std::uint16_t read[2] = {};
  EXPECT_EQ(modbus_read_registers(*client, 40, 2, read), -1);  // beyond the slave's 32 registers
  EXPECT_EQ(errno, EMBXILADD);
}

TEST_F(ForwardTest, SilentSlaveIsAnswered0x0BAfterTheRetries) {
  TcpClient client(forwarder_->port(), 18);  // nobody on the line has address 18
  std::uint16_t value = 0;
  const auto before = forwarder_->engine().counters().timeouts;
  EXPECT_EQ(modbus_read_registers(*client, 0, 1, &value), -1);
  EXPECT_EQ(errno, EMBXGTAR);
  EXPECT_EQ(forwarder_->engine().counters().timeouts, before + 3);  // first attempt + 2 retries
}

// mbusd's default: a broadcast gets no answer. A libmodbus client (which waits for one) times
// out, the frame is on the line all the same, and the connection's next request gets its own
// answer — not a late one meant for the broadcast.
TEST_F(ForwardTest, UnitZeroIsAnRtuBroadcastWithoutAnAnswer) {
  TcpClient client(forwarder_->port(), 0);
  modbus_set_response_timeout(*client, 0, 300'000);
  EXPECT_EQ(modbus_write_register(*client, 7, 77), -1);
  EXPECT_EQ(errno, ETIMEDOUT);
  EXPECT_TRUE(eventually([&] { return slave_->holding(7) == 77; }));
  modbus_set_slave(*client, 17);
  std::uint16_t read[2] = {};
  ASSERT_EQ(modbus_read_registers(*client, 7, 2, read), 2) << modbus_strerror(errno);
  EXPECT_EQ(read[0], 77);
  // Nobody can answer a broadcast read: still 0x0A at once, without touching the line.
  modbus_set_slave(*client, 0);
  EXPECT_EQ(modbus_read_registers(*client, 7, 1, read), -1);
  EXPECT_EQ(errno, EMBXGPATH);
}

class ForwardAnsweringBroadcastsTest : public ForwardTest {
  BroadcastReply broadcast_reply() const override { return BroadcastReply::Answer; }
};

// --reply-on-broadcast (mbusd -b): for clients that wait for an answer, as libmodbus does.
TEST_F(ForwardAnsweringBroadcastsTest, UnitZeroIsAnRtuBroadcastAnsweredOnceSent) {
  TcpClient client(forwarder_->port(), 0);
  ASSERT_EQ(modbus_write_register(*client, 7, 77), 1) << modbus_strerror(errno);
  EXPECT_TRUE(eventually([&] { return slave_->holding(7) == 77; }));
  const std::uint16_t values[2] = {1, 2};
  ASSERT_EQ(modbus_write_registers(*client, 12, 2, values), 2) << modbus_strerror(errno);
  EXPECT_TRUE(eventually([&] { return slave_->holding(13) == 2; }));
  // Nobody can answer a broadcast read: 0x0A without touching the line.
  std::uint16_t read = 0;
  EXPECT_EQ(modbus_read_registers(*client, 7, 1, &read), -1);
  EXPECT_EQ(errno, EMBXGPATH);
}

TEST_F(ForwardTest, UnitsAbove247AreRefusedWith0x0A) {
  TcpClient client(forwarder_->port(), 250);
  std::uint16_t read = 0;
  EXPECT_EQ(modbus_read_registers(*client, 0, 1, &read), -1);
  EXPECT_EQ(errno, EMBXGPATH);
}

TEST_F(ForwardTest, RetriesAnAnswerDamagedOnTheLine) {
  TcpClient client(forwarder_->port(), 17);
  ASSERT_EQ(modbus_write_register(*client, 1, 555), 1) << modbus_strerror(errno);
  const auto before = forwarder_->engine().counters();
  line_.corrupt_next_from_b();
  std::uint16_t value = 0;
  ASSERT_EQ(modbus_read_registers(*client, 1, 1, &value), 1) << modbus_strerror(errno);
  EXPECT_EQ(value, 555);
  const auto after = forwarder_->engine().counters();
  EXPECT_EQ(after.checksum_errors, before.checksum_errors + 1);
  // The damaged answer's retry; one more only where a loaded machine heard an answer after its
  // 50 ms (the line's two retries bound it).
  EXPECT_GE(after.retries, before.retries + 1);
  EXPECT_LE(after.retries, before.retries + 2);
}

TEST_F(ForwardTest, ManyClientsAtOnceAreSerialisedOnTheLine) {
  constexpr int kClients = 8;
  constexpr int kRounds = 20;
  std::atomic<int> failures{0};
  std::vector<std::thread> clients;
  for (int c = 0; c < kClients; ++c) {
    clients.emplace_back([&, c] {
      TcpClient client(forwarder_->port(), 17);
      for (int round = 0; round < kRounds; ++round) {
        const auto value = static_cast<std::uint16_t>(c * 1000 + round);
        std::uint16_t back = 0;
        if (modbus_write_register(*client, c, value) != 1 || modbus_read_registers(*client, c, 1, &back) != 1 ||
            back != value) {
          ++failures;
        }
      }
    });
  }
  for (auto& thread : clients) thread.join();
  EXPECT_EQ(failures.load(), 0);
  for (int c = 0; c < kClients; ++c) EXPECT_EQ(slave_->holding(c), c * 1000 + kRounds - 1);
}

TEST(Broadcast, WritesAreAnsweredAsTheSlaveWouldReadsAreNot) {
  using protocol::Bytes;
  EXPECT_EQ(broadcast_answer(Bytes{0x06, 0x00, 0x07, 0x00, 0x4D}), (Bytes{0x06, 0x00, 0x07, 0x00, 0x4D}));
  EXPECT_EQ(broadcast_answer(Bytes{0x10, 0x00, 0x0C, 0x00, 0x02, 0x04, 0x00, 0x01, 0x00, 0x02}),
            (Bytes{0x10, 0x00, 0x0C, 0x00, 0x02}));
  EXPECT_EQ(broadcast_answer(Bytes{0x41}), (Bytes{0x41}));
  EXPECT_FALSE(broadcast_answer(Bytes{0x03, 0x00, 0x00, 0x00, 0x01}));
  EXPECT_FALSE(broadcast_answer(Bytes{0x17, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x02, 0x00, 0x00}));
}

// The forwarder in front of simulated SMSMB servos: the servos' own answers, FC04 refused by
// the servo itself (docs/PROTOCOL.md §1.3), not by the gateway.
TEST(ForwardToServos, SmsmbServoAnswersComeBackAsTheyAre) {
  simulator::BusOptions bus_options;
  bus_options.servos = {{1, modbus_map::TableId::Smsmb, protocol::BusProtocol::ModbusRtu, 56'000}};
  simulator::SimulatedBus bus(bus_options);
  bus.start();
  ForwardOptions options;
  options.serial = SerialSettings{bus.slave_path(), 56'000};  // a rate libmodbus alone cannot set
  options.rtu.byte_timeout = 20ms;
  options.response_timeout = 50ms;
  options.listen = {"127.0.0.1", 0};
  ForwardGateway forwarder(options);
  forwarder.start();
  TcpClient client(forwarder.port(), 1);
  std::uint16_t values[2] = {};
  ASSERT_EQ(modbus_read_registers(*client, 0x0A, 2, values), 2) << modbus_strerror(errno);
  EXPECT_EQ(values[0], 1);  // ID
  EXPECT_EQ(values[1], 4);  // baud code 4 = 56000
  EXPECT_EQ(modbus_read_input_registers(*client, 0x100, 1, values), -1);
  EXPECT_EQ(errno, EMBXILFUN);
  // A function without a length rule in libmodbus (0x0B, get comm event counter): the servo's
  // 0x01 comes back as it is, framed by silence on the RTU side.
  const std::uint8_t event_counter[] = {1, 0x0B};
  ASSERT_GT(modbus_send_raw_request(*client, event_counter, sizeof event_counter), 0);
  std::array<std::uint8_t, MODBUS_TCP_MAX_ADU_LENGTH> answer{};
  ASSERT_EQ(modbus_receive_confirmation(*client, answer.data()), 9) << modbus_strerror(errno);  // MBAP + 2
  EXPECT_EQ(answer[7], 0x8B);
  EXPECT_EQ(answer[8], 0x01);
  forwarder.stop();
}

}  // namespace
}  // namespace sms::gateway
