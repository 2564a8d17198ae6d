// The bus around the servos: wire timing, line speed, mixed buses, fault injection, the
// state file, the control socket and the sms-sim program.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <signal.h>
#include <stdlib.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>

#include "protocol/feetech.h"
#include "protocol/stream_decoder.h"
#include "simulator/control_server.h"
#include "tests/simulator/sim_fixture.h"

namespace sms::simulator::testing {
namespace {

using protocol::kD55dFormat;
using protocol::kFeetechFormat;
using Clock = std::chrono::steady_clock;

std::string temporary_path(const std::string& name) {
  return (std::filesystem::temp_directory_path() / ("sms-sim-test-" + std::to_string(::getpid()) + "-" + name))
      .string();
}

double elapsed_ms(Clock::time_point since) {
  return std::chrono::duration<double, std::milli>(Clock::now() - since).count();
}

// --- wire timing ------------------------------------------------------------------------

TEST(SimulatedBusTiming, ReplyNeverArrivesBeforeItsWireTime) {
  BusOptions options = quick_options({sts(1, 38'400)});
  options.timing = true;
  Rig rig(options);
  // READ 56..70: 8 request + 21 reply bytes at 38400 = 7.55 ms, + the factory return delay 0,
  // which acts as 50 × 2 µs (wiki memory-sts address 7).
  const double wire_ms = (8 + 21) * 10.0 / 38'400 * 1000 + 0.1;
  for (int round = 0; round < 10; ++round) {
    const auto sent = Clock::now();
    rig.host->send(protocol::encode(kFeetechFormat, protocol::read(1, 56, 15)));
    const Bytes reply = rig.host->receive_exactly(21);
    const double took = elapsed_ms(sent);
    ASSERT_EQ(reply.size(), 21U);
    EXPECT_GE(took, wire_ms) << "round " << round;
    EXPECT_LT(took, wire_ms + 150) << "round " << round << ": timing should not add much more than the wire";
  }
}

TEST(SimulatedBusTiming, ReturnDelayIsPartOfTheWireTime) {
  BusOptions options = quick_options({d55d(1, 115'200)});
  options.timing = true;
  Rig rig(options);
  // d55d return delay: address 5 × 500 µs; 20 -> 10 ms.
  ASSERT_EQ(rig.host->transact(kD55dFormat, protocol::write(1, 5, Bytes{20})), status(1, 0));
  const auto sent = Clock::now();
  ASSERT_EQ(rig.host->transact(kD55dFormat, protocol::ping(1)), status(1, 0, {0}));
  EXPECT_GE(elapsed_ms(sent), 10.0 + (6 + 7) * 10.0 / 115'200 * 1000);
}

TEST(SimulatedBusTiming, SyncReadRepliesFollowEachOtherWithTheirReturnDelays) {
  BusOptions options = quick_options({sts(1, 115'200), sts(2, 115'200), sts(3, 115'200)});
  options.timing = true;
  Rig rig(options);
  const std::vector<std::uint8_t> ids{1, 2, 3};
  const auto sent = Clock::now();
  rig.host->send(protocol::encode(kFeetechFormat, protocol::feetech::sync_read(56, 15, ids)));
  const Bytes replies = rig.host->receive_exactly(3 * 21);
  const double took = elapsed_ms(sent);
  ASSERT_EQ(replies.size(), 63U);
  // docs/PROTOCOL.md §5: (8 + N) request bytes + N × (6 + L) reply bytes + N return delays (100 µs each:
  // the factory 0 acts as 50 × 2 µs).
  EXPECT_GE(took, (11 + 63) * 10.0 / 115'200 * 1000 + 3 * 0.1);
  const auto packets = decode_all(kFeetechFormat, replies);
  ASSERT_EQ(packets.size(), 3U);
  EXPECT_EQ(packets[0].id, 1);
  EXPECT_EQ(packets[1].id, 2);
  EXPECT_EQ(packets[2].id, 3);
}

TEST(SimulatedBusTiming, NoTimingAnswersWithoutWaitingForTheWire) {
  Rig rig(quick_options({d55d(1, 2'400)}));
  // READ 30..44 at 2400 bit/s: 8 + 21 bytes = 121 ms on the wire, plus 8 ms return delay.
  const auto sent = Clock::now();
  rig.host->send(protocol::encode(kD55dFormat, protocol::read(1, 30, 15)));
  ASSERT_EQ(rig.host->receive_exactly(21).size(), 21U);
  EXPECT_LT(elapsed_ms(sent), 80.0);
}

TEST(SimulatedBusTiming, TimingCanBeSwitchedAtRunTime) {
  Rig rig(quick_options({d55d(1, 2'400)}));
  rig.bus->set_timing(true);
  const auto sent = Clock::now();
  rig.host->send(protocol::encode(kD55dFormat, protocol::read(1, 30, 15)));
  ASSERT_EQ(rig.host->receive_exactly(21).size(), 21U);
  EXPECT_GE(elapsed_ms(sent), (8 + 21) * 10.0 / 2'400 * 1000 + 8.0);
}

// --- line speed -------------------------------------------------------------------------

TEST(SimulatedBusLine, ServoIsSilentWhenTheHostSpeedDiffersFromItsBaud) {
  Rig rig(quick_options({sts(1)}), 115'200);
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(50)));
  rig.host->set_baud(1'000'000);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
}

TEST(SimulatedBusLine, MixedBusAnswersEachServoAtItsOwnRateAndProtocol) {
  Rig rig(quick_options({sts(1, 1'000'000), sts(2, 115'200), smsmb(3, 115'200), d55d(4, 115'200), sms1(5, 76'800)}));
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(2), std::chrono::milliseconds(30)));

  rig.host->set_baud(115'200);
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(2)), status(2, 0));
  EXPECT_EQ(rig.host->transact(kD55dFormat, protocol::ping(4)), status(4, 0, {0}));
  rig.host->send({0x03, 0x11, 0xC1, 0x4C});  // FC 0x11 to slave 3
  EXPECT_EQ(rig.host->receive_answer(8), (Bytes{0x03, 0x11, 0x03, 0x03, 0x00, 0x00, 0x0C, 0x6F}));

  rig.host->set_baud(76'800);  // not a standard termios rate: BOTHER
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(5)), status(5, 0));
}

TEST(SimulatedBusLine, HostClosingItsEndDoesNotHangTheBusUp) {
  Rig rig(quick_options({sts(1)}));
  rig.host.reset();
  HostPort again(rig.bus->slave_path(), 1'000'000);
  EXPECT_EQ(again.transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
}

// A host killed while it holds the pty exclusively (TIOCEXCL, as the gateway does; then SIGKILL,
// or a crash) does not leave it busy for the next one, as a real adapter's claim ends with its
// last close: the simulator's own descriptor keeps the pty alive, not the dead host's claim.
TEST(SimulatedBusLine, AHostKilledWhileHoldingThePtyExclusivelyLeavesItFreeForTheNext) {
  Rig rig(quick_options({sts(1)}));
  rig.host.reset();
  const std::string path = rig.bus->slave_path();
  // Root opens an exclusive tty anyway: then the next host opens it as nobody, who may not.
  if (::geteuid() == 0) {
    ASSERT_EQ(::chmod(path.c_str(), 0666), 0) << std::strerror(errno);
  }
  std::array<int, 2> ready{};
  ASSERT_EQ(::pipe(ready.data()), 0);
  const pid_t holder = ::fork();
  ASSERT_GE(holder, 0);
  if (holder == 0) {
    const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY);
    if (fd < 0 || ::ioctl(fd, TIOCEXCL) != 0) ::_exit(1);
    [[maybe_unused]] const auto written = ::write(ready[1], "x", 1);
    ::pause();
    ::_exit(0);
  }
  ::close(ready[1]);
  char byte = 0;
  ASSERT_EQ(::read(ready[0], &byte, 1), 1) << "the holder could not open the pty exclusively";
  ::close(ready[0]);
  ASSERT_EQ(::kill(holder, SIGKILL), 0);
  ASSERT_EQ(::waitpid(holder, nullptr, 0), holder);

  // 0: opened; 3: EBUSY; others: could not try.
  const auto next_host_opens = [&] {
    const pid_t next = ::fork();
    if (next == 0) {
      if (::geteuid() == 0 && ::setuid(65534) != 0) ::_exit(2);
      const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
      ::_exit(fd >= 0 ? 0 : errno == EBUSY ? 3 : 4);
    }
    int status = 0;
    if (next < 0 || ::waitpid(next, &status, 0) != next) return -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  };
  int last = -1;
  EXPECT_TRUE(eventually([&] { return (last = next_host_opens()) == 0; }, "the next host opens the pty"))
      << "the last try ended with " << last << " (3: EBUSY, the dead host's claim)";
  HostPort again(path, 1'000'000);
  EXPECT_EQ(again.transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
}

TEST(SimulatedBusLine, LinkPointsAtThePtyAndGoesAwayAtStop) {
  BusOptions options = quick_options({sts(1)});
  options.link = temporary_path("link");
  {
    SimulatedBus bus(options);
    bus.start();
    EXPECT_EQ(std::filesystem::read_symlink(options.link).string(), bus.slave_path());
    HostPort host(options.link, 1'000'000);
    EXPECT_EQ(host.transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
  }
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(options.link)));
}

TEST(SimulatedBusLine, AttachesToAnExistingSerialDevice) {
  // A second pty stands in for a USB adapter: the simulator answers on its slave end, the
  // test talks on the master end.
  const int master = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
  ASSERT_GE(master, 0);
  ASSERT_EQ(::grantpt(master), 0);
  ASSERT_EQ(::unlockpt(master), 0);
  BusOptions options = quick_options({sts(1, 115'200)});
  options.device = ::ptsname(master);
  SimulatedBus bus(options);
  bus.start();
  EXPECT_EQ(bus.slave_path(), options.device);
  const Bytes ping{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB};
  ASSERT_EQ(::write(master, ping.data(), ping.size()), static_cast<ssize_t>(ping.size()));
  Bytes reply(6);
  std::size_t got = 0;
  const auto give_up = Clock::now() + std::chrono::seconds(1);
  while (got < reply.size() && Clock::now() < give_up) {
    pollfd pfd{master, POLLIN, 0};
    if (::poll(&pfd, 1, 50) <= 0) continue;
    const ssize_t n = ::read(master, reply.data() + got, reply.size() - got);
    if (n > 0) got += static_cast<std::size_t>(n);
  }
  EXPECT_EQ(reply, (Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC}));
  bus.stop();
  ::close(master);
}

TEST(SimulatedBusLine, WrongTableForTheProtocolIsRefusedWithTheReason) {
  BusOptions options = quick_options({{1, modbus_map::TableId::Sts, protocol::BusProtocol::D55d, 115'200}});
  try {
    SimulatedBus bus(options);
    FAIL() << "constructed";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("feetech"), std::string::npos) << error.what();
  }
}

TEST(SimulatedBusLine, BaudOutsideTheProtocolTableIsRefusedWithTheValidRates) {
  try {
    SimulatedBus bus(quick_options({sts(1, 12'345)}));
    FAIL() << "constructed";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("12345"), std::string::npos) << error.what();
  }
}

// --- faults ---------------------------------------------------------------------------------

TEST(SimulatedBusFaults, OfflineServoIsSilentUntilOnlineAgain) {
  Rig rig(quick_options({sts(1), sts(2)}));
  rig.bus->set_offline(2, true);
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(2), std::chrono::milliseconds(50)));
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
  rig.bus->set_offline(2, false);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(2)), status(2, 0));
}

TEST(SimulatedBusFaults, DropProbabilityOneDropsEveryReplyButTheWriteStillLands) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->set_drop_probability(1.0);
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::write(1, 41, Bytes{7}), std::chrono::milliseconds(50)));
  rig.bus->set_drop_probability(0.0);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::read(1, 41, 1)), status(1, 0, {7}));
  EXPECT_EQ(rig.bus->stats().dropped, 1U);
}

TEST(SimulatedBusFaults, DropProbabilityHalfDropsAboutHalf) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->set_drop_probability(0.5);
  int answered = 0;
  for (int round = 0; round < 40; ++round) {
    if (rig.host->transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(25))) ++answered;
  }
  EXPECT_GT(answered, 8);
  EXPECT_LT(answered, 32);
}

TEST(SimulatedBusFaults, CorruptedReplyFailsItsChecksumAndTheNextIsClean) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->corrupt_next_replies(1);
  rig.host->send(protocol::encode(kFeetechFormat, protocol::read(1, 56, 2)));
  const Bytes corrupted = rig.host->receive_answer(8);
  EXPECT_EQ(corrupted.size(), 8U);
  EXPECT_NE(corrupted, (Bytes{0xFF, 0xFF, 0x01, 0x04, 0x00, 0x00, 0x08, 0xF2}));
  EXPECT_TRUE(decode_all(kFeetechFormat, corrupted).empty()) << hex(corrupted);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::read(1, 56, 2)), status(1, 0, {0x00, 0x08}));
}

TEST(SimulatedBusFaults, CorruptProbabilityOneSpoilsEveryReply) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->set_corrupt_probability(1.0);
  for (int round = 0; round < 5; ++round) {
    EXPECT_TRUE(rig.host->transact_all(kFeetechFormat, protocol::ping(1)).empty()) << "round " << round;
  }
  EXPECT_EQ(rig.bus->stats().corrupted, 5U);
  rig.bus->set_corrupt_probability(0.0);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
}

TEST(SimulatedBusFaults, LateServoAnswersAfterTheHostGaveUp) {
  Rig rig(quick_options({sts(1), sts(2)}));
  // Half a second late: far past the host's 30 ms, and far past servo 1's answer to the host's
  // next request, which a loaded machine may send tens of milliseconds late (with a delay of
  // 80 ms it sent it after the late answer, or while it was on the wire, where the simulator's
  // bus made the two collide: no frame at all).
  rig.bus->set_reply_delay(2, std::chrono::milliseconds(500));
  const auto sent = Clock::now();
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(2), std::chrono::milliseconds(30)));
  // The late reply turns up when the host has moved on to servo 1: both answers are awaited, as
  // long as a loaded machine holds the simulator's thread back.
  const auto replies = rig.host->transact_expecting(kFeetechFormat, protocol::ping(1), 2);
  EXPECT_GE(elapsed_ms(sent), 500.0);
  EXPECT_EQ(replies, (std::vector<protocol::Packet>{status(1, 0), status(2, 0)}));
  EXPECT_EQ(rig.bus->stats().collisions, 0U);
}

TEST(SimulatedBusFaults, GarbledServoSpoilsOnlyItsOwnReplies) {
  Rig rig(quick_options({sts(1), sts(2)}));
  rig.bus->set_garbled(2, true);
  for (int round = 0; round < 3; ++round) {
    EXPECT_TRUE(rig.host->transact_all(kFeetechFormat, protocol::ping(2)).empty()) << "round " << round;
    EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0)) << "round " << round;
  }
  // A write to the garbled servo still lands: only its answer is damaged.
  rig.host->send(protocol::encode(kFeetechFormat, protocol::write(2, 42, Bytes{0xDC, 0x05})));
  (void)rig.host->receive_answer(6);
  EXPECT_EQ(rig.bus->read_field(2, "goal_position"), std::optional<std::int32_t>{1500});
  rig.bus->set_garbled(2, false);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(2)), status(2, 0));
}

TEST(SimulatedBusFaults, DuplicateIdRepliesCollideOnTheWire) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->add_duplicate(1);
  rig.host->send(protocol::encode(kFeetechFormat, protocol::read(1, 56, 2)));
  const Bytes collided = rig.host->receive_answer(8);
  EXPECT_EQ(collided.size(), 8U) << "both start together: one frame's worth of garbled characters";
  EXPECT_TRUE(decode_all(kFeetechFormat, collided).empty()) << hex(collided);
  EXPECT_EQ(rig.bus->stats().collisions, 1U);
  EXPECT_EQ(rig.bus->servos().size(), 2U);
}

// A servo answers one request after the other: two requests arriving in one read (sent back to
// back) get two whole replies, in turn, and never collide with each other; only two different
// servos can collide (above). Vendor SDKs send a PING and a READ together this way.
TEST(SimulatedBusLine, BackToBackRequestsToOneServoAreAnsweredInTurn) {
  for (const bool timing : {false, true}) {
    BusOptions options = quick_options({sts(1)});
    options.timing = timing;
    Rig rig(options);
    const auto expected_read = rig.bus->read_memory(1, 56, 2);
    ASSERT_TRUE(expected_read);
    Bytes both = protocol::encode(kFeetechFormat, protocol::ping(1));
    const Bytes read = protocol::encode(kFeetechFormat, protocol::read(1, 56, 2));
    both.insert(both.end(), read.begin(), read.end());
    rig.host->send(both);
    const Bytes replies = rig.host->receive_answer(6 + 8);  // the PING's status, the READ's with 2 bytes
    const auto frames = decode_all(kFeetechFormat, replies);
    ASSERT_EQ(frames.size(), 2U) << "timing " << timing << ": " << hex(replies);
    EXPECT_EQ(frames[0], status(1, 0));
    EXPECT_EQ(frames[1].id, 1U);
    EXPECT_EQ(frames[1].params.size(), 2U);

    const Bytes ping = protocol::encode(kFeetechFormat, protocol::ping(1));
    Bytes pings = ping;
    pings.insert(pings.end(), ping.begin(), ping.end());
    rig.host->send(pings);
    const Bytes pongs = rig.host->receive_answer(6 + 6);
    EXPECT_EQ(decode_all(kFeetechFormat, pongs), (std::vector<protocol::Packet>{status(1, 0), status(1, 0)}))
        << "timing " << timing << ": " << hex(pongs);
    EXPECT_EQ(rig.bus->stats().collisions, 0U);
  }
}

// A late servo stays in order: when its lateness ends, the new answers wait behind the late ones.
TEST(SimulatedBusFaults, LateServoAnswersInTheOrderAsked) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->set_reply_delay(1, std::chrono::milliseconds(60));
  rig.host->send(protocol::encode(kFeetechFormat, protocol::read(1, 56, 2)));
  std::this_thread::sleep_for(std::chrono::milliseconds(5));
  rig.bus->set_reply_delay(1, std::chrono::milliseconds(0));
  rig.host->send(protocol::encode(kFeetechFormat, protocol::ping(1)));
  const Bytes replies = rig.host->receive_answer(8 + 6);
  const auto frames = decode_all(kFeetechFormat, replies);
  ASSERT_EQ(frames.size(), 2U) << hex(replies);
  EXPECT_EQ(frames[0].params.size(), 2U) << "the READ was asked first";
  EXPECT_EQ(frames[1], status(1, 0));
}

TEST(SimulatedBusFaults, ErrorBitsAreClearedWithZero) {
  Rig rig(quick_options({sts(1)}));
  rig.bus->set_error_bits(1, protocol::feetech::error_bit::kOverload);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, protocol::feetech::error_bit::kOverload));
  rig.bus->set_error_bits(1, 0);
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
}

// --- state file ---------------------------------------------------------------------------

TEST(SimulatedBusStateFile, UnlockedEepromWritesSurviveARestartLockedOnesDoNot) {
  const std::string path = temporary_path("state");
  std::filesystem::remove(path);
  BusOptions options = quick_options({sts(1), sts(2)});
  options.state_file = path;
  {
    Rig rig(options);
    ASSERT_EQ(rig.host->transact(kFeetechFormat, protocol::write(1, 13, Bytes{60})), status(1, 0));  // locked
    ASSERT_EQ(rig.host->transact(kFeetechFormat, protocol::write(2, 55, Bytes{0})), status(2, 0));
    ASSERT_EQ(rig.host->transact(kFeetechFormat, protocol::write(2, 13, Bytes{61})), status(2, 0));
    ASSERT_EQ(rig.host->transact(kFeetechFormat, protocol::write(2, 5, Bytes{12})), status(2, 0));
  }
  Rig again(options);
  EXPECT_EQ(again.host->transact(kFeetechFormat, protocol::read(1, 13, 1)), status(1, 0, {70}));
  EXPECT_EQ(again.host->transact(kFeetechFormat, protocol::read(12, 13, 1)), status(12, 0, {61}))
      << "slot 2 comes back with its saved ID";
  EXPECT_FALSE(again.host->transact(kFeetechFormat, protocol::ping(2), std::chrono::milliseconds(30)));
  std::filesystem::remove(path);
}

TEST(SimulatedBusStateFile, UnreadableStateFileIsReportedWithItsLine) {
  const std::string path = temporary_path("bad-state");
  {
    std::ofstream out(path);
    out << "# comment\neeprom zero sts id=1\n";
  }
  BusOptions options = quick_options({sts(1)});
  options.state_file = path;
  SimulatedBus bus(options);
  try {
    bus.start();
    FAIL() << "started";
  } catch (const std::runtime_error& error) {
    EXPECT_NE(std::string(error.what()).find(path + ":2"), std::string::npos) << error.what();
  }
  std::filesystem::remove(path);
}

// --- control socket ---------------------------------------------------------------------

class ControlClient {
 public:
  explicit ControlClient(const std::string& path) {
    fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_un address{};
    address.sun_family = AF_UNIX;
    std::strncpy(address.sun_path, path.c_str(), sizeof address.sun_path - 1);
    for (int attempt = 0; attempt < 100; ++attempt) {
      if (::connect(fd_, reinterpret_cast<const sockaddr*>(&address), sizeof address) == 0) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    throw std::runtime_error("cannot connect to " + path);
  }
  ~ControlClient() { ::close(fd_); }
  std::string ask(const std::string& line) {
    const std::string request = line + "\n";
    EXPECT_EQ(::send(fd_, request.data(), request.size(), MSG_NOSIGNAL), static_cast<ssize_t>(request.size()));
    std::string reply;
    char byte = 0;
    while (::recv(fd_, &byte, 1, 0) == 1 && byte != '\n') reply += byte;
    return reply;
  }

 private:
  int fd_ = -1;
};

TEST(SimulatedBusControl, SocketCommandsInjectFaultsAndReadMemory) {
  Rig rig(quick_options({sts(1), sts(2)}));
  const std::string path = temporary_path("control.sock");
  ControlServer server(*rig.bus, path);
  ControlClient control(path);

  EXPECT_EQ(control.ask("get 1 56 2"), "00 08");
  EXPECT_EQ(control.ask("set 1 41 0a"), "ok");
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::read(1, 41, 1)), status(1, 0, {10}));
  EXPECT_EQ(control.ask("field 1 acceleration"), "10");

  EXPECT_EQ(control.ask("offline 2"), "ok");
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(2), std::chrono::milliseconds(30)));
  EXPECT_EQ(control.ask("list"), "1:sts:feetech:1000000 2:sts:feetech:1000000:offline");
  EXPECT_EQ(control.ask("online 2"), "ok");
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(2)), status(2, 0));

  EXPECT_EQ(control.ask("error 2 0x20"), "ok");
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(2)), status(2, 0x20));
  EXPECT_EQ(control.ask("error 2 0"), "ok");

  EXPECT_EQ(control.ask("drop 1"), "ok");
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  EXPECT_EQ(control.ask("drop 0"), "ok");

  EXPECT_EQ(control.ask("late 1 60"), "ok");
  const auto sent = Clock::now();
  EXPECT_EQ(rig.host->transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
  EXPECT_GE(elapsed_ms(sent), 60.0);
  EXPECT_EQ(control.ask("late 1 0"), "ok");

  EXPECT_EQ(control.ask("corrupt-next"), "ok");
  EXPECT_FALSE(rig.host->transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  EXPECT_EQ(control.ask("duplicate 1"), "ok");
  EXPECT_EQ(control.ask("timing off"), "ok");
  EXPECT_EQ(control.ask("stats").rfind("requests=", 0), 0U);

  EXPECT_EQ(control.ask("offline 9"), "error: no servo has ID 9");
  EXPECT_EQ(control.ask("drop 2").rfind("error: usage: drop P", 0), 0U);
  EXPECT_EQ(control.ask("get 1 250 10").rfind("error: ", 0), 0U);
  EXPECT_EQ(control.ask("frobnicate").rfind("error: unknown command 'frobnicate'", 0), 0U);
  EXPECT_EQ(control.ask("garble 1"), "error: usage: garble ID on|off");
  EXPECT_EQ(control.ask("error 1 300"), "error: usage: error ID BITS   (BITS 0-255, e.g. 0x04)");
  // The help is made from the command table: every command, in its form.
  EXPECT_EQ(
      control.ask("help"),
      "commands: offline ID | online ID | drop P | corrupt P | corrupt-next [N] | garble ID on|off | late ID MS | "
      "error ID BITS | duplicate ID | timing on|off | get ID ADDR COUNT | set ID ADDR HEX... | field ID NAME | "
      "motion ID | list | stats | holds | help");
}

// --- the sms-sim program ------------------------------------------------------------------

std::string run_and_capture(const std::string& command) {
  std::string output;
  FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) return output;
  char buffer[512];
  while (std::fgets(buffer, sizeof buffer, pipe) != nullptr) output += buffer;
  ::pclose(pipe);
  return output;
}

TEST(SmsSimProgram, HelpDocumentsEveryOption) {
  const std::string help = run_and_capture(std::string(SMS_SIM_PATH) + " --help");
  for (const char* option : {"--protocol",
                             "--table",
                             "--ids",
                             "--baud",
                             "--servo",
                             "--link",
                             "--device",
                             "--no-timing",
                             "--state-file",
                             "--control",
                             "--drop",
                             "--corrupt",
                             "--late",
                             "--offline",
                             "--error",
                             "--duplicate",
                             "modbus-rtu",
                             "smsmb",
                             "sts, sms1 and scs",
                             "scs 48 = 0",
                             "get ID ADDR COUNT"}) {
    EXPECT_NE(help.find(option), std::string::npos) << option << " missing from --help";
  }
}

TEST(SmsSimProgram, PrintsThePtyPathServesItAndStopsOnSigterm) {
  const std::string link = temporary_path("prog-link");
  const std::string socket_path = temporary_path("prog.sock");
  int out[2];
  ASSERT_EQ(::pipe(out), 0);
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    ::dup2(out[1], STDOUT_FILENO);
    ::close(out[0]);
    ::close(out[1]);
    ::execl(SMS_SIM_PATH, SMS_SIM_PATH, "--protocol", "feetech", "--table", "sts", "--ids", "1,3", "--baud", "1000000",
            "--link", link.c_str(), "--no-timing", "--control", socket_path.c_str(), "--late", "3:40",
            static_cast<char*>(nullptr));
    ::_exit(127);
  }
  ::close(out[1]);
  std::string line;
  char byte = 0;
  while (::read(out[0], &byte, 1) == 1 && byte != '\n') line += byte;
  ::close(out[0]);
  EXPECT_EQ(line.rfind("/dev/pts/", 0), 0U) << line;

  {
    HostPort host(link, 1'000'000);
    EXPECT_EQ(host.transact(kFeetechFormat, protocol::ping(1)), status(1, 0));
    const auto sent = Clock::now();
    EXPECT_EQ(host.transact(kFeetechFormat, protocol::ping(3)), status(3, 0));
    EXPECT_GE(elapsed_ms(sent), 40.0) << "--late 3:40";
    ControlClient control(socket_path);
    EXPECT_EQ(control.ask("offline 1"), "ok");
    EXPECT_FALSE(host.transact(kFeetechFormat, protocol::ping(1), std::chrono::milliseconds(30)));
  }
  ASSERT_EQ(::kill(child, SIGTERM), 0);
  int status_code = 0;
  ASSERT_EQ(::waitpid(child, &status_code, 0), child);
  EXPECT_TRUE(WIFEXITED(status_code) && WEXITSTATUS(status_code) == 0);
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(link)));
}

TEST(SmsSimProgram, BadArgumentsSayWhatIsWrong) {
  const std::string output =
      run_and_capture(std::string(SMS_SIM_PATH) + " --protocol d55d --table sts 2>&1; echo exit=$?");
  EXPECT_NE(output.find("spoken over feetech"), std::string::npos) << output;
  EXPECT_EQ(output.find("exit=0"), std::string::npos) << output;
}

}  // namespace
}  // namespace sms::simulator::testing
