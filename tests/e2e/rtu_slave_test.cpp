// The upstream Modbus RTU port (docs/RTU_PANELS.md) as a panel meets it: sms-sim with sts
// servos on a pty, sms-gateway --config with modbus_rtu_slave ports on pty pairs (socat, as two
// RS-485 adapters joined by a cable), and RTU masters nobody here wrote: libmodbus, mbpoll,
// pymodbus. Counters are read from /metrics; every wait polls a condition with a deadline.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <modbus/modbus.h>
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include "protocol/modbus_rtu.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"
#include "tests/support/processes.h"

// Its own namespace: the test files of e2e_tests compile in batches (unity build), where the
// helpers of one file's anonymous namespace would meet another's of the same name.
namespace sms::e2e::rtu_slave_test {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using test::http_request;
using test::parse_exposition;

// Two pty ends joined by socat: the gateway opens one, the master the other.
class PtyPair {
 public:
  PtyPair(const TempDir& dir, const std::string& name)
      : gateway_end_(dir.file(name + "-up")), master_end_(dir.file(name + "-panel")) {
    plug();
  }
  ~PtyPair() { unplug(); }

  const std::string& gateway_end() const { return gateway_end_; }
  const std::string& master_end() const { return master_end_; }

  void plug() {
    socat_ = std::make_unique<ChildProcess>(std::vector<std::string>{
        "/usr/bin/socat", "pty,raw,echo=0,link=" + gateway_end_, "pty,raw,echo=0,link=" + master_end_});
    if (!eventually([&] { return std::filesystem::exists(gateway_end_) && std::filesystem::exists(master_end_); })) {
      throw std::runtime_error("socat made no pty pair:\n" + socat_->output());
    }
  }
  // The adapter is pulled out: both ptys vanish.
  void unplug() {
    if (!socat_) return;
    socat_->signal(SIGTERM);
    socat_->wait_exit(10s);
    socat_.reset();
    std::error_code ignored;
    std::filesystem::remove(gateway_end_, ignored);
    std::filesystem::remove(master_end_, ignored);
  }

 private:
  std::string gateway_end_;
  std::string master_end_;
  std::unique_ptr<ChildProcess> socat_;
};

// A libmodbus RTU master on a pty end.
class RtuClient {
 public:
  RtuClient(const std::string& device, int baud, char parity, int unit, double timeout_s = 1.0) {
    ctx_ = modbus_new_rtu(device.c_str(), baud, parity, 8, 1);
    if (ctx_ == nullptr) throw std::runtime_error("modbus_new_rtu failed");
    const auto seconds = static_cast<std::uint32_t>(timeout_s);
    modbus_set_response_timeout(ctx_, seconds, static_cast<std::uint32_t>((timeout_s - seconds) * 1e6));
    if (modbus_connect(ctx_) != 0) {
      const std::string reason = modbus_strerror(errno);
      modbus_free(ctx_);
      throw std::runtime_error("open " + device + ": " + reason);
    }
    modbus_set_slave(ctx_, unit);
  }
  ~RtuClient() {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
  RtuClient(const RtuClient&) = delete;
  RtuClient& operator=(const RtuClient&) = delete;

  void set_unit(int unit) { modbus_set_slave(ctx_, unit); }
  modbus_t* context() { return ctx_; }
  // The Modbus exception code of the last failure, -1 for anything else (a timeout).
  static int failure() { return errno > MODBUS_ENOBASE && errno < MODBUS_ENOBASE + 0x20 ? errno - MODBUS_ENOBASE : -1; }

  Answer<std::uint16_t> read_input(int address, int count) {
    Answer<std::uint16_t> answer;
    answer.values.resize(static_cast<std::size_t>(count));
    if (modbus_read_input_registers(ctx_, address, count, answer.values.data()) < 0) return failed<std::uint16_t>();
    return answer;
  }
  Answer<std::uint16_t> read_holding(int address, int count) {
    Answer<std::uint16_t> answer;
    answer.values.resize(static_cast<std::size_t>(count));
    if (modbus_read_registers(ctx_, address, count, answer.values.data()) < 0) return failed<std::uint16_t>();
    return answer;
  }
  Answer<std::uint16_t> write_register(int address, std::uint16_t value) {
    if (modbus_write_register(ctx_, address, value) < 0) return failed<std::uint16_t>();
    return {};
  }
  // Bytes straight onto the line, and what comes back within `wait`.
  void send_raw(const std::vector<std::uint8_t>& bytes) {
    ASSERT_EQ(::write(modbus_get_socket(ctx_), bytes.data(), bytes.size()), static_cast<ssize_t>(bytes.size()));
  }
  std::vector<std::uint8_t> read_raw(std::chrono::milliseconds wait) {
    std::vector<std::uint8_t> got;
    const auto deadline = std::chrono::steady_clock::now() + wait;
    for (;;) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      if (left.count() <= 0) return got;
      pollfd fd{modbus_get_socket(ctx_), POLLIN, 0};
      if (::poll(&fd, 1, static_cast<int>(left.count())) <= 0) return got;
      std::uint8_t buffer[256];
      const ssize_t n = ::read(fd.fd, buffer, sizeof buffer);
      if (n <= 0) return got;
      got.insert(got.end(), buffer, buffer + n);
    }
  }

 private:
  template <typename T>
  static Answer<T> failed() {
    Answer<T> answer;
    answer.exception = failure();
    answer.error = modbus_strerror(errno);
    return answer;
  }
  modbus_t* ctx_ = nullptr;
};

std::string run(const std::vector<std::string>& argv, int* exit_code) {
  ChildProcess process(argv);
  *exit_code = process.wait_exit(30s).value_or(-1);
  return process.output();
}

// Four upstream ports on one gateway: 9600, 115200 and 1 000 000 bit/s 8E1 with every unit and
// role operate; a read-only one for unit 2 with a long fixed t3.5 (200 ms: gaps a test can make
// on a loaded machine).
// The gateway unit is 247 so RTU masters that stop at 247 (libmodbus, mbpoll) reach it.
constexpr const char* kConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020", gateway_unit_id: 247}
buses:
  - {name: arm, device: "@ARM@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: 100, retries: 1}
servos:
  - {bus: arm, id: 1, table: sts}
  - {bus: arm, id: 2, table: sts}
logging: {metrics_listen: "127.0.0.1:0"}
modbus_rtu_slave:
  - {device: "@P9600@", baud: 9600}
  - {device: "@P115200@", baud: 115200, parity: even, reopen_period_ms: 100}
  - {device: "@P1M@", baud: 1000000}
  - {device: "@PREAD@", baud: 19200, parity: none, stop_bits: 2, frame_gap: 200000us, units: [2], role: read}
)";

class RtuSlave : public ::testing::Test {
 protected:
  RtuSlave()
      : arm_(dir_, "arm", {"--servo", "1:sts", "--servo", "2:sts"}),
        p9600_(dir_, "p9600"),
        p115200_(dir_, "p115200"),
        p1m_(dir_, "p1m"),
        pread_(dir_, "pread") {
    std::string yaml = substitute(kConfig, "@ARM@", arm_.pty());
    yaml = substitute(yaml, "@P9600@", p9600_.gateway_end());
    yaml = substitute(yaml, "@P115200@", p115200_.gateway_end());
    yaml = substitute(yaml, "@P1M@", p1m_.gateway_end());
    yaml = substitute(yaml, "@PREAD@", pread_.gateway_end());
    gateway_ = std::make_unique<GatewayProcess>(GatewayProcess::with_config(dir_, yaml, 1));
    const std::string marker = "/healthz on http://127.0.0.1:";
    const auto line = gateway_->process().wait_for_line(marker, 15s);
    if (!line) throw std::runtime_error("no metrics endpoint:\n" + gateway_->process().output());
    metrics_port_ = static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
    for (const PtyPair* port : {&p9600_, &p115200_, &p1m_, &pread_}) {
      if (!gateway_->process().wait_for_line("rtu slave " + port->gateway_end() + ": open at", 10s)) {
        throw std::runtime_error(port->gateway_end() + " not open:\n" + gateway_->process().output());
      }
    }
    wait_until_polled(gateway_->port(), 1);
    wait_until_polled(gateway_->port(), 2);
  }

  // A counter of one port from /metrics (sms_gateway_rtu_slave_<name>), -1 when absent.
  long counter(const PtyPair& port, const std::string& name) {
    const auto metrics = parse_exposition(http_request(metrics_port_, "GET", "/metrics").body);
    const std::string value =
        metrics.value("sms_gateway_rtu_slave_" + name + "{device=\"" + port.gateway_end() + "\"}");
    return value == "(absent)" ? -1 : std::stol(value);
  }

  TempDir dir_;
  SimProcess arm_;
  PtyPair p9600_, p115200_, p1m_, pread_;
  std::unique_ptr<GatewayProcess> gateway_;
  std::uint16_t metrics_port_ = 0;
};

TEST_F(RtuSlave, LibmodbusMasterReadsFeedbackWritesAGoalAndSeesItMoveAtEveryRate) {
  struct Case {
    PtyPair* port;
    int baud;
    std::uint16_t goal;
  };
  for (const Case& rate : {Case{&p9600_, 9600, 1100}, Case{&p115200_, 115200, 2200}, Case{&p1m_, 1000000, 3300}}) {
    SCOPED_TRACE(rate.baud);
    RtuClient master(rate.port->master_end(), rate.baud, 'E', 1);
    const auto feedback = master.read_input(56, 15);  // present position .. (the poll cache)
    ASSERT_TRUE(feedback.ok()) << feedback.error << "\n" << gateway_->process().output();
    EXPECT_EQ(feedback.values[0], arm_.field(1, "present_position"));
    ASSERT_TRUE(master.write_register(42, rate.goal).ok());  // goal position, live
    EXPECT_EQ(arm_.field(1, "goal_position"), rate.goal);
    EXPECT_EQ(master.read_holding(42, 1).values, std::vector<std::uint16_t>{rate.goal});
    EXPECT_TRUE(eventually([&] {
      const auto position = master.read_input(56, 1);
      return position.ok() && position.values[0] == rate.goal;
    })) << "servo 1 did not move to "
        << rate.goal;
    // Exceptions as over TCP: past the table, a read-only field.
    EXPECT_EQ(master.read_holding(1000, 1).exception, 0x02);
    EXPECT_EQ(master.write_register(56, 1).exception, 0x02);
    EXPECT_GE(counter(*rate.port, "answers_total"), 6);
  }
}

TEST_F(RtuSlave, MbpollReadsAndWrites) {
  const std::string device = p115200_.master_end();
  int exit_code = 0;
  const std::string write = run({"/usr/bin/mbpoll", "-m", "rtu", "-b", "115200", "-P", "even", "-a", "2", "-t", "4",
                                 "-r", "43", "-1", device, "1777"},
                                &exit_code);
  ASSERT_EQ(exit_code, 0) << write;
  EXPECT_EQ(arm_.field(2, "goal_position"), 1777);
  ASSERT_TRUE(eventually([&] { return arm_.field(2, "present_position") == 1777; }));
  std::string feedback;
  EXPECT_TRUE(eventually([&] {
    feedback = run({"/usr/bin/mbpoll", "-m", "rtu", "-b", "115200", "-P", "even", "-a", "2", "-t", "3", "-r", "57",
                    "-c", "15", "-1", device},
                   &exit_code);
    return exit_code == 0 && feedback.find("[57]: \t1777") != std::string::npos;
  })) << feedback;
  EXPECT_NE(feedback.find("[71]:"), std::string::npos) << feedback;
}

TEST_F(RtuSlave, TcpClientAndRtuMasterOnOneBusEachKeepTheirOrder) {
  constexpr int kRounds = 40;
  std::atomic<int> tcp_done{0};
  std::atomic<int> rtu_done{0};
  std::string tcp_error;
  std::string rtu_error;
  std::thread tcp([&] {
    ModbusClient client(gateway_->port(), 1);
    for (int i = 0; i < kRounds; ++i) {
      const auto value = static_cast<std::uint16_t>(1000 + i);
      if (!client.write_register(42, value).ok()) return void(tcp_error = "write " + std::to_string(i));
      // Its own last write is what it reads back: nothing of the other master's in between.
      const auto back = client.read_holding(42, 1);
      if (!back.ok() || back.values[0] != value) return void(tcp_error = "read back " + std::to_string(i));
      ++tcp_done;
    }
  });
  std::thread rtu([&] {
    RtuClient master(p115200_.master_end(), 115200, 'E', 2);
    for (int i = 0; i < kRounds; ++i) {
      const auto value = static_cast<std::uint16_t>(3000 + i);
      if (!master.write_register(42, value).ok()) return void(rtu_error = "write " + std::to_string(i));
      const auto back = master.read_holding(42, 1);
      if (!back.ok() || back.values[0] != value) return void(rtu_error = "read back " + std::to_string(i));
      ++rtu_done;
    }
  });
  tcp.join();
  rtu.join();
  EXPECT_EQ(tcp_error, "");
  EXPECT_EQ(rtu_error, "");
  EXPECT_EQ(tcp_done.load(), kRounds);  // neither starved the other
  EXPECT_EQ(rtu_done.load(), kRounds);
  EXPECT_EQ(arm_.field(1, "goal_position"), 1000 + kRounds - 1);
  EXPECT_EQ(arm_.field(2, "goal_position"), 3000 + kRounds - 1);
}

TEST_F(RtuSlave, GarbageAndCrcErrorsAreDroppedCountedAndTheNextRequestIsAnswered) {
  // On the port with the long t3.5, so a loaded machine cannot split a frame by accident.
  RtuClient master(pread_.master_end(), 19200, 'N', 2);
  const long dropped = counter(pread_, "dropped_frames_total");
  const long crc = counter(pread_, "crc_errors_total");
  master.send_raw({0x55, 0xAA, 0x01});  // noise: shorter than any frame
  ASSERT_TRUE(eventually([&] { return counter(pread_, "dropped_frames_total") == dropped + 1; }));
  auto request = protocol::rtu::frame(2, std::vector<std::uint8_t>{0x03, 0x00, 0x2A, 0x00, 0x01});
  request.back() ^= 0xFF;  // a wrong CRC
  master.send_raw(request);
  ASSERT_TRUE(eventually([&] { return counter(pread_, "crc_errors_total") == crc + 1; }));
  EXPECT_TRUE(master.read_raw(50ms).empty());  // neither was answered
  const auto answer = master.read_holding(42, 1);
  EXPECT_TRUE(answer.ok()) << answer.error;
  EXPECT_EQ(counter(pread_, "dropped_frames_total"), dropped + 1);
  EXPECT_EQ(counter(pread_, "crc_errors_total"), crc + 1);
}

TEST_F(RtuSlave, AFrameWithASilenceOverT15InsideIsDropped) {
  // The read-only port's t3.5 is 200 ms, so its t1.5 is 86 ms: a 120 ms pause does not split
  // the frame in two but breaks it. The gap the gateway sees is the one socat relays; on a loaded
  // machine a relay can stretch or shrink it past either bound, so an attempt whose gap did not
  // come out as sent (answered, or split in two) is made again.
  RtuClient master(pread_.master_end(), 19200, 'N', 2);
  const auto request = protocol::rtu::frame(2, std::vector<std::uint8_t>{0x03, 0x00, 0x2A, 0x00, 0x01});
  std::string attempts;
  bool dropped_as_one_broken_frame = false;
  for (int attempt = 0; attempt < 5 && !dropped_as_one_broken_frame; ++attempt) {
    const long dropped = counter(pread_, "dropped_frames_total");
    const long crc = counter(pread_, "crc_errors_total");
    master.send_raw(std::vector<std::uint8_t>(request.begin(), request.begin() + 4));
    std::this_thread::sleep_for(120ms);  // the gap under test, not a wait for state
    master.send_raw(std::vector<std::uint8_t>(request.begin() + 4, request.end()));
    const auto answer = master.read_raw(600ms);  // t3.5 and more: an answer would have come
    dropped_as_one_broken_frame = answer.empty() && counter(pread_, "dropped_frames_total") == dropped + 1 &&
                                  counter(pread_, "crc_errors_total") == crc;
    attempts += " [answer " + std::to_string(answer.size()) + " bytes, dropped +" +
                std::to_string(counter(pread_, "dropped_frames_total") - dropped) + ", crc +" +
                std::to_string(counter(pread_, "crc_errors_total") - crc) + "]";
  }
  EXPECT_TRUE(dropped_as_one_broken_frame) << attempts;
  master.send_raw(request);  // the same frame whole is answered
  const auto answer = master.read_raw(1s);
  ASSERT_EQ(answer.size(), 7u);
  EXPECT_EQ(answer[0], 2);
  EXPECT_EQ(answer[1], 0x03);
}

TEST_F(RtuSlave, TheAnswerStartsNoEarlierThanT35AfterTheRequest) {
  // 9600 bit/s 8E1: 11 bits a character, t3.5 = 38.5 bit times = 4.01 ms. Measured from the
  // master's write, which reaches the gateway a little later still (socat): a lower bound.
  RtuClient master(p9600_.master_end(), 9600, 'E', 1);
  const auto t35 = std::chrono::nanoseconds(38'500'000'000LL / 9600);
  for (int i = 0; i < 5; ++i) {
    const auto request = protocol::rtu::frame(1, std::vector<std::uint8_t>{0x03, 0x00, 0x2A, 0x00, 0x01});
    const auto sent = std::chrono::steady_clock::now();
    master.send_raw(request);
    pollfd fd{modbus_get_socket(master.context()), POLLIN, 0};
    ASSERT_EQ(::poll(&fd, 1, 1000), 1);
    EXPECT_GE(std::chrono::steady_clock::now() - sent, t35);
    EXPECT_EQ(master.read_raw(100ms).size(), 7u);  // the whole answer
  }
}

TEST_F(RtuSlave, ABroadcastWriteIsCarriedOutAndNeverAnswered) {
  RtuClient master(p115200_.master_end(), 115200, 'E', 1);
  const long broadcasts = counter(p115200_, "broadcasts_total");
  master.send_raw(protocol::rtu::frame(0, std::vector<std::uint8_t>{0x06, 0x00, 0x2A, 0x0B, 0xB8}));  // goal := 3000
  EXPECT_TRUE(
      eventually([&] { return arm_.field(1, "goal_position") == 3000 && arm_.field(2, "goal_position") == 3000; }));
  ASSERT_TRUE(eventually([&] { return counter(p115200_, "broadcasts_total") == broadcasts + 1; }));
  EXPECT_TRUE(master.read_raw(100ms).empty());
  EXPECT_TRUE(master.read_holding(42, 1).ok());  // the line goes on
}

TEST_F(RtuSlave, UnitsThePortDoesNotServeGetSilenceAndTheRoleRefusesWrites) {
  RtuClient master(pread_.master_end(), 19200, 'N', 1, 0.6);
  const long silent = counter(pread_, "silent_units_total");
  EXPECT_EQ(master.read_holding(42, 1).exception, -1);  // unit 1 is not this port's: a timeout
  master.set_unit(9);                                   // nor is an unconfigured unit
  EXPECT_EQ(master.read_holding(42, 1).exception, -1);
  EXPECT_EQ(counter(pread_, "silent_units_total"), silent + 2);
  master.set_unit(2);
  EXPECT_TRUE(master.read_holding(42, 1).ok());
  EXPECT_EQ(master.write_register(42, 100).exception, 0x01);  // role read
  EXPECT_EQ(counter(pread_, "role_refusals_total"), 1);
}

TEST_F(RtuSlave, TheEStopLatchedOverTcpRefusesRtuMotionWritesWith0x04) {
  ModbusClient gateway_unit(gateway_->port(), 247);
  RtuClient master(p115200_.master_end(), 115200, 'E', 1);
  ASSERT_TRUE(master.write_register(42, 1500).ok());
  ASSERT_TRUE(gateway_unit.write_coils(1, {1}).ok());  // e-stop
  EXPECT_EQ(master.write_register(42, 2500).exception, 0x04);
  EXPECT_TRUE(master.read_holding(42, 1).ok());  // reads go on
  master.set_unit(247);
  EXPECT_TRUE(master.read_input(0, 3).ok());  // the gateway unit over RTU: its version
  ASSERT_TRUE(gateway_unit.write_coils(1, {0}).ok());
  master.set_unit(1);
  EXPECT_TRUE(master.write_register(42, 2500).ok());
  EXPECT_EQ(arm_.field(1, "goal_position"), 2500);
}

// The counter's help says "carried out": a broadcast the e-stop refuses on every unit is not.
TEST_F(RtuSlave, ABroadcastTheEStopRefusesIsNotCountedAsCarriedOut) {
  ModbusClient gateway_unit(gateway_->port(), 247);
  RtuClient master(p115200_.master_end(), 115200, 'E', 1);
  ASSERT_TRUE(master.write_register(42, 1700).ok());
  const long broadcasts = counter(p115200_, "broadcasts_total");
  ASSERT_TRUE(gateway_unit.write_coils(1, {1}).ok());                                                 // e-stop
  master.send_raw(protocol::rtu::frame(0, std::vector<std::uint8_t>{0x06, 0x00, 0x2A, 0x0B, 0xB8}));  // goal := 3000
  EXPECT_TRUE(master.read_raw(100ms).empty());  // never answered (and the line is quiet before the next)
  // The port takes one request at a time: once this read is answered, the broadcast is done.
  ASSERT_TRUE(master.read_holding(42, 1).ok());
  // (The e-stop's safe stop set the goal to where the servo stood; the broadcast's 3000 never came.)
  EXPECT_NE(arm_.field(1, "goal_position"), 3000);
  EXPECT_NE(arm_.field(2, "goal_position"), 3000);
  EXPECT_EQ(counter(p115200_, "broadcasts_total"), broadcasts);
  ASSERT_TRUE(gateway_unit.write_coils(1, {0}).ok());
  master.send_raw(protocol::rtu::frame(0, std::vector<std::uint8_t>{0x06, 0x00, 0x2A, 0x0B, 0xB8}));
  EXPECT_TRUE(eventually([&] { return arm_.field(1, "goal_position") == 3000; }));
  EXPECT_TRUE(eventually([&] { return counter(p115200_, "broadcasts_total") == broadcasts + 1; }));
}

TEST_F(RtuSlave, AServoThatStopsAnsweringIs0x0BNotSilence) {
  // The unit exists and the gateway is alive: the panel learns at once that the servo is gone.
  RtuClient master(p115200_.master_end(), 115200, 'E', 2);
  ASSERT_EQ(arm_.control("offline 2"), "ok");
  EXPECT_TRUE(eventually([&] { return master.read_holding(42, 1).exception == 0x0B; }));
  ASSERT_EQ(arm_.control("online 2"), "ok");
  EXPECT_TRUE(eventually([&] { return master.read_holding(42, 1).ok(); }));
}

TEST_F(RtuSlave, AnUnpluggedPortIsLostAndServesAgainOnceReplugged) {
  p115200_.unplug();
  ASSERT_TRUE(gateway_->process().wait_for_line("port lost", 10s)) << gateway_->process().output();
  EXPECT_TRUE(eventually([&] { return counter(p115200_, "up") == 0 && counter(p115200_, "port_lost_total") == 1; }));
  {
    RtuClient other(p9600_.master_end(), 9600, 'E', 1);  // the other ports go on
    EXPECT_TRUE(other.read_holding(42, 1).ok());
  }
  p115200_.plug();
  ASSERT_TRUE(gateway_->process().wait_for_line("reopened", 10s)) << gateway_->process().output();
  RtuClient master(p115200_.master_end(), 115200, 'E', 1);
  EXPECT_TRUE(master.read_holding(42, 1).ok());
  EXPECT_EQ(counter(p115200_, "up"), 1);
}

TEST(RtuSlaveCommandLine, PymodbusSerialClientOnSimulateWithTheFlag) {
  TempDir dir;
  PtyPair pair(dir, "panel");
  GatewayProcess gateway({"--simulate", "--rtu-slave", pair.gateway_end() + ":115200:none"}, 1);
  ASSERT_TRUE(gateway.process().wait_for_line("rtu slave " + pair.gateway_end() + ": open at", 10s));
  wait_until_polled(gateway.port(), 1);
  int exit_code = 0;
  const std::string output = run({"/usr/bin/python3", std::string(SMS_SOURCE_DIR) + "/tests/e2e/pymodbus_rtu.py",
                                  pair.master_end(), "115200", "N", "2345"},
                                 &exit_code);
  EXPECT_EQ(exit_code, 0) << output << gateway.process().output();
  EXPECT_NE(output.find("goal 2345"), std::string::npos) << output;
  EXPECT_NE(output.find("unit 99 silent"), std::string::npos) << output;
}

TEST(RtuSlaveCommandLine, ABusDeviceCannotBeAnUpstreamPortToo) {
  TempDir dir;
  const std::string path = dir.file("gateway.yaml");
  std::ofstream(path) << "buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}\n"
                         "servos: []\n";
  int exit_code = 0;
  const std::string output = run({bin("sms-gateway"), "--config", path, "--rtu-slave", "/dev/ttyUSB0"}, &exit_code);
  EXPECT_EQ(exit_code, 2) << output;
  EXPECT_NE(output.find("is the device of bus `arm`"), std::string::npos) << output;
}

TEST(RtuSlaveCommandLine, TheShippedPanelExampleChecks) {
  int exit_code = 0;
  const std::string output =
      run({bin("sms-gateway"), "--check-config", std::string(SMS_SOURCE_DIR) + "/config/examples/rtu-panel.yaml"},
          &exit_code);
  EXPECT_EQ(exit_code, 0) << output;
  EXPECT_NE(output.find("upstream Modbus RTU port"), std::string::npos) << output;
}

}  // namespace
}  // namespace sms::e2e::rtu_slave_test
