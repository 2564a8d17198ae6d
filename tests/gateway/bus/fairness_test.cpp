// Fair scheduling on every bus protocol against the simulator on a pty: a live read is
// answered while writes flood the bus, the poll cache keeps being refreshed under a client
// flood on a modbus-rtu bus too, and a servo that sets a refusal bit in every answer shows one
// status byte, not a different one after each write. Bounded in count and time; no timed
// assertion: the read must come back while the flood still runs.
#include <gtest/gtest.h>

#include <atomic>
#include <mutex>
#include <string>
#include <thread>

#include "gateway/bus/bus_engine.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using modbus_map::TableId;
using protocol::Bytes;
using testing::eventually;
using testing::transact;

using testing::EngineKind;

class Fairness : public ::testing::TestWithParam<EngineKind> {
 protected:
  void start(bool poll) {
    const EngineKind& kind = GetParam();
    simulator_ = std::make_unique<simulator::SimulatedBus>(testing::simulated_servos({1, 2, 3}, kind.table, kind.baud));
    simulator_->start();
    BusSettings settings = testing::bus_settings(simulator_->slave_path(), {1, 2, 3}, kind.table, kind.baud);
    settings.poll = poll;
    settings.discover = poll;
    settings.queue_depth = 32;
    engine_ = make_bus_engine(settings);
    engine_->start();
    ASSERT_TRUE(engine_->bus_up());
    if (poll) {  // braces: ASSERT_TRUE expands to an if/else (GCC's -Wdangling-else)
      ASSERT_TRUE(eventually([&] { return engine_->discovered(); }));
    }
  }
  void TearDown() override {
    flooding_ = false;
    if (flood_.joinable()) flood_.join();
    if (engine_) engine_->stop();
    if (simulator_) simulator_->stop();
  }

  // Keeps `depth` writes queued at all times until stopped or `limit` writes were answered.
  void flood_writes(unsigned depth, unsigned limit) {
    flooding_ = true;
    flood_ = std::thread([this, depth, limit] {
      std::atomic<unsigned> in_flight{0};
      unsigned sent = 0;
      while (flooding_ && written_ < limit) {
        while (in_flight < depth && sent < limit) {
          ++in_flight;
          ++sent;
          const auto id = static_cast<std::uint8_t>(1 + sent % 3);
          engine_->submit(WriteOp{id, GetParam().field, GetParam().value(static_cast<std::uint8_t>(sent % 200))},
                          Priority::ClientWrite, [&](BusResult) {
                            ++written_;
                            --in_flight;
                          });
        }
        std::this_thread::sleep_for(100us);
      }
      while (in_flight > 0) std::this_thread::sleep_for(1ms);
    });
  }

  std::unique_ptr<simulator::SimulatedBus> simulator_;
  std::unique_ptr<BusEngine> engine_;
  std::thread flood_;
  std::atomic<bool> flooding_{false};
  std::atomic<unsigned> written_{0};
};

TEST_P(Fairness, LiveReadIsAnsweredWhileWritesFloodTheBus) {
  constexpr unsigned kFloodLimit = 3000;
  start(false);
  flood_writes(16, kFloodLimit);
  ASSERT_TRUE(eventually([&] { return written_.load() >= 20; }));  // the flood is on
  std::atomic<bool> answered{false};
  unsigned written_when_answered = 0;
  engine_->submit(ReadOp{1, GetParam().read.address, GetParam().read.count}, Priority::ClientRead,
                  [&](BusResult result) {
                    EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
                    written_when_answered = written_.load();
                    answered = true;
                  });
  ASSERT_TRUE(eventually([&] { return answered.load() || written_.load() >= kFloodLimit; }, 60s));
  EXPECT_TRUE(answered.load()) << "the read waited behind the whole flood";
  EXPECT_LT(written_when_answered, kFloodLimit) << "the read was answered only after the flood ended";
  flooding_ = false;
}

TEST_P(Fairness, PollCacheIsRefreshedUnderAClientFlood) {
  constexpr unsigned kFloodLimit = 3000;
  start(true);
  flood_writes(16, kFloodLimit);
  ASSERT_TRUE(eventually([&] { return written_.load() >= 20; }));
  const auto before = engine_->counters().poll_cycles;
  ASSERT_TRUE(
      eventually([&] { return engine_->counters().poll_cycles >= before + 3 || written_.load() >= kFloodLimit; }, 60s));
  EXPECT_GE(engine_->counters().poll_cycles, before + 3);
  EXPECT_LT(written_.load(), kFloodLimit) << "polls ran only after the flood ended";
  flooding_ = false;
}

INSTANTIATE_TEST_SUITE_P(BothEngines, Fairness,
                         ::testing::Values(EngineKind{"feetech_sts", TableId::Sts, 1'000'000, 41, {56, 15}},
                                           EngineKind{"d55d", TableId::D55d, 115'200, 34, {36, 8}},
                                           EngineKind{"modbus_rtu_smsmb", TableId::Smsmb, 115'200, 0x82, {0x100, 8}}),
                         [](const ::testing::TestParamInfo<EngineKind>& info) { return info.param.name; });

// One rule for the status byte: a servo that sets the refusal bit (feetech bit 4) in every answer
// shows the same register-1000 byte after polls and after refused writes; the log says nothing.
TEST(StatusByte, ARefusalBitInEveryAnswerDoesNotFlipTheRecordedStatus) {
  testing::LogCapture log;
  simulator::SimulatedBus bus(testing::simulated_servos({1}));
  bus.start();
  BusSettings settings = testing::bus_settings(bus.slave_path(), {1});
  auto engine = make_bus_engine(settings);
  engine->start();
  ASSERT_TRUE(eventually([&] { return engine->discovered(); }));
  bus.set_error_bits(1, 0x10);
  std::vector<std::uint8_t> seen;
  for (int round = 0; round < 10; ++round) {
    transact(*engine, WriteOp{1, 41, {static_cast<std::uint8_t>(10 + round)}});
    seen.push_back(engine->cache().state(1)->counters.last_status);
    const auto cycles = engine->counters().poll_cycles;
    ASSERT_TRUE(eventually([&] { return engine->counters().poll_cycles > cycles + 1; }));
    seen.push_back(engine->cache().state(1)->counters.last_status);
  }
  for (const auto status : seen) EXPECT_EQ(status, seen.front());
  EXPECT_FALSE(log.contains("status byte 0x00 -> 0x10")) << log.text();
  engine->stop();
  bus.stop();
}

// The rule for the status byte, on both packet protocols: a servo that reports a condition (bit 0,
// feetech: voltage, d55d: over-temperature) together with a refusal bit in every answer shows the
// condition alone in register 1000 after polls and after refused writes alike, and the log says
// so once when the condition appears and once when it goes, however many answers came between.
struct StatusCase {
  std::string name;
  TableId table;
  std::uint32_t baud;
  std::uint16_t field;         // a RAM field written by the test
  std::uint8_t refusal_bit;    // set in every answer: writes are refused
  std::uint8_t condition_bit;  // the servo's condition, recorded and logged
};
inline void PrintTo(const StatusCase& c, std::ostream* out) { *out << c.name; }

class StatusByteRule : public ::testing::TestWithParam<StatusCase> {};

std::size_t occurrences(const std::string& text, const std::string& needle) {
  std::size_t count = 0;
  for (auto at = text.find(needle); at != std::string::npos; at = text.find(needle, at + needle.size())) ++count;
  return count;
}

TEST_P(StatusByteRule, OneByteForEveryAnswerKindAndOneLogLinePerChangeOfCondition) {
  const StatusCase& param = GetParam();
  testing::LogCapture log;
  simulator::SimulatedBus bus(testing::simulated_servos({1}, param.table, param.baud));
  bus.start();
  auto engine = make_bus_engine(testing::bus_settings(bus.slave_path(), {1}, param.table, param.baud));
  engine->start();
  ASSERT_TRUE(eventually([&] { return engine->discovered(); }));
  const auto status = [&] { return engine->cache().state(1)->counters.last_status; };
  const auto two_poll_cycles = [&] {
    const auto cycles = engine->counters().poll_cycles;
    return eventually([&] { return engine->counters().poll_cycles > cycles + 1; });
  };
  // A write every attempt of which went unanswered while the machine held the simulator an
  // attempt's time is made again (at most five times): the status byte is what is tested here.
  const auto write = [&](std::uint8_t value) {
    for (int attempt = 1;; ++attempt) {
      const auto sent = std::chrono::steady_clock::now();
      const BusResult result = transact(*engine, WriteOp{1, param.field, {value}});
      if (result.status != BusStatus::Timeout || attempt == 5 || !testing::simulator_held(bus, 50ms, sent)) {
        return result;
      }
    }
  };
  ASSERT_EQ(write(1).status, BusStatus::Ok);  // the servo answers writes

  bus.set_error_bits(1, static_cast<std::uint8_t>(param.refusal_bit | param.condition_bit));
  for (std::uint8_t round = 0; round < 5; ++round) {
    EXPECT_EQ(write(round).status, BusStatus::ServoRefused);
    EXPECT_EQ(status(), param.condition_bit) << "after a refused write, round " << int{round};
    ASSERT_TRUE(two_poll_cycles());
    EXPECT_EQ(status(), param.condition_bit) << "after polls, round " << int{round};
  }
  bus.set_error_bits(1, param.refusal_bit);  // the condition is gone, the refusals stay
  for (std::uint8_t round = 0; round < 3; ++round) {
    ASSERT_TRUE(two_poll_cycles());
    EXPECT_EQ(status(), 0) << "after polls, round " << int{round};
    EXPECT_EQ(write(round).status, BusStatus::ServoRefused);
    EXPECT_EQ(status(), 0) << "after a refused write, round " << int{round};
  }
  const std::string text = log.text();
  EXPECT_EQ(occurrences(text, "servo 1 status byte 0x00 -> 0x01"), 1U) << text;
  EXPECT_EQ(occurrences(text, "servo 1 status byte 0x01 -> 0x00"), 1U) << text;
  EXPECT_EQ(occurrences(text, "status byte"), 2U) << text;
  engine->stop();
  bus.stop();
}

INSTANTIATE_TEST_SUITE_P(PacketProtocols, StatusByteRule,
                         ::testing::Values(StatusCase{"feetech_sts", TableId::Sts, 1'000'000, 41, 0x10, 0x01},
                                           StatusCase{"d55d", TableId::D55d, 115'200, 34, 0x20, 0x01}),
                         [](const ::testing::TestParamInfo<StatusCase>& info) { return info.param.name; });

}  // namespace
}  // namespace sms::gateway
