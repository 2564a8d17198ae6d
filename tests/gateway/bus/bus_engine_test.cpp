// The packet bus engine (EngineCore<PacketTransactor>) against the real simulator on a pty:
// round trips of every operation, refusals, timeouts and retries, damaged and late replies,
// queue order and back-pressure, custom bit rates. Polling is off here (poll_*_test.cpp covers
// it) so that every frame on the line is one the test asked for.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <mutex>
#include <string>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace testing;
using modbus_map::TableId;
using protocol::Bytes;

class BusEngineTest : public ::testing::Test {
 protected:
  void start(std::vector<std::uint8_t> ids, TableId table = TableId::Sts, std::uint32_t baud = 1'000'000,
             std::uint32_t engine_baud = 0) {
    simulator_ = std::make_unique<simulator::SimulatedBus>(simulated_servos(ids, table, baud));
    simulator_->start();
    settings_ = bus_settings(simulator_->slave_path(), ids, table, engine_baud == 0 ? baud : engine_baud);
    settings_.poll = false;
    settings_.discover = false;
    tweak(settings_);
    engine_ = make_bus_engine(settings_);
    engine_->start();
    ASSERT_TRUE(engine_->bus_up());
  }
  virtual void tweak(BusSettings&) {}
  void TearDown() override {
    if (engine_) engine_->stop();
    if (simulator_) simulator_->stop();
  }
  Bytes memory(std::uint8_t id, std::uint16_t address, std::uint16_t count) {
    return simulator_->read_memory(id, address, count).value_or(Bytes{});
  }

  BusSettings settings_;
  std::unique_ptr<simulator::SimulatedBus> simulator_;
  std::unique_ptr<BusEngine> engine_;
};

// --- round trips -------------------------------------------------------------------------------

TEST_F(BusEngineTest, ReadReturnsTheServosBytes) {
  start({1, 2});
  // sts identity as the simulator's SM40BL reports it: model 8.42 at 3-4, ID at 5.
  const BusResult model = transact(*engine_, ReadOp{1, 3, 3}, Priority::ClientRead);
  ASSERT_EQ(model.status, BusStatus::Ok) << model.detail;
  EXPECT_EQ(model.data, (Bytes{0x08, 0x2A, 0x01}));
  EXPECT_EQ(model.servo_error, 0);

  const BusResult id = transact(*engine_, ReadOp{2, 5, 1}, Priority::ClientRead);
  ASSERT_EQ(id.status, BusStatus::Ok) << id.detail;
  EXPECT_EQ(id.data, (Bytes{0x02}));

  const auto counters = engine_->counters();
  EXPECT_EQ(counters.frames_ok, 2U);
  // An answer a loaded machine hears too late is asked again, within the retries: allowed.
  EXPECT_LE(counters.retries, 2 * settings_.retries);
  EXPECT_EQ(counters.transactions, 2U);
  EXPECT_EQ(engine_->cache().state(1)->counters.replies_ok, 1U);
}

TEST_F(BusEngineTest, WriteIsAcknowledgedAndLandsInTheServo) {
  start({1});
  // Goal position 1000 = 0x03E8, low byte first (sts).
  const BusResult result = transact(*engine_, WriteOp{1, 42, {0xE8, 0x03}});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_TRUE(result.data.empty());
  EXPECT_EQ(memory(1, 42, 2), (Bytes{0xE8, 0x03}));
  EXPECT_EQ(engine_->counters().frames_ok, 1U);  // the WRITE's answer was consumed
}

TEST_F(BusEngineTest, StagedWriteWaitsForActionThenRuns) {
  start({1, 2});
  const Bytes before = memory(1, 42, 2);
  ASSERT_NE(before, (Bytes{0x00, 0x04}));
  const BusResult staged = transact(*engine_, WriteOp{1, 42, {0x00, 0x04}, true});
  ASSERT_EQ(staged.status, BusStatus::Ok) << staged.detail;
  EXPECT_EQ(memory(1, 42, 2), before);

  const BusResult action = transact(*engine_, ActionOp{});
  ASSERT_EQ(action.status, BusStatus::Ok) << action.detail;
  // ACTION is a broadcast: nothing to wait for, but the next READ is answered after it ran.
  const BusResult goal = transact(*engine_, ReadOp{1, 42, 2}, Priority::ClientRead);
  ASSERT_EQ(goal.status, BusStatus::Ok) << goal.detail;
  EXPECT_EQ(goal.data, (Bytes{0x00, 0x04}));
}

TEST_F(BusEngineTest, SyncWriteSetsEveryListedServoInOneFrame) {
  start({1, 2, 3});
  const auto requests_before = simulator_->stats().requests;
  SyncWriteOp sync{42, 2, {{1, {0x00, 0x02}}, {3, {0x00, 0x06}}}};
  const BusResult result = transact(*engine_, sync);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  ASSERT_TRUE(eventually([&] { return memory(3, 42, 2) == Bytes{0x00, 0x06}; }));
  EXPECT_EQ(memory(1, 42, 2), (Bytes{0x00, 0x02}));
  EXPECT_NE(memory(2, 42, 2), (Bytes{0x00, 0x02}));
  EXPECT_EQ(simulator_->stats().requests - requests_before, 1U);
  EXPECT_EQ(engine_->counters().frames_ok, 0U);  // no answer to a broadcast
}

TEST_F(BusEngineTest, WriteWithoutReplyCompletesOnceOnTheWire) {
  start({1});
  const BusResult result = transact(*engine_, WriteOp{1, 41, {0x07}, false, false});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  // The servo answered anyway (its response level is 1): the stray answer is flushed before
  // the next transmit and the READ gets its own answer.
  const BusResult read = transact(*engine_, ReadOp{1, 41, 1}, Priority::ClientRead);
  ASSERT_EQ(read.status, BusStatus::Ok) << read.detail;
  EXPECT_EQ(read.data, (Bytes{0x07}));
}

TEST_F(BusEngineTest, PingIsAnswered) {
  start({4});
  const BusResult result = transact(*engine_, PingOp{4});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.servo_error, 0);
}

TEST_F(BusEngineTest, PingAnswerByteForByteTheRequestIsTakenOnALineThatDoesNotEcho) {
  start({1});
  // ERROR 0x01 (voltage) makes the answer FF FF 01 02 01 FB: the PING request itself. On a line
  // never seen to echo it is the servo's answer (bus_echo_test.cpp: behind an echoing adapter
  // the same bytes alone are only the echo).
  simulator_->set_error_bits(1, 0x01);
  const BusResult result = transact(*engine_, PingOp{1});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.servo_error, 0x01);
}

TEST_F(BusEngineTest, AnAnswerWithBit4IsARefusalWithTheServosErrorByte) {
  start({1});
  // Doc 001 names status bit 4 "angle / out of range"; current Feetech firmware leaves it unused
  // (docs/DECISIONS.md "Vendor fidelity"). A servo that sets it is taken at its word.
  simulator_->set_error_bits(1, 0x10);
  const BusResult result = transact(*engine_, WriteOp{1, 41, {0x01}});
  EXPECT_EQ(result.status, BusStatus::ServoRefused) << result.detail;
  EXPECT_EQ(result.servo_error & 0x10, 0x10);
  EXPECT_NE(result.detail.find("servo 1 refused WRITE at 41"), std::string::npos) << result.detail;
  EXPECT_EQ(engine_->counters().retries, 0U);  // a refusal is an answer, not a reason to retry
}

TEST_F(BusEngineTest, WriteToAReadOnlyFieldIsAnsweredAndLandsNothing) {
  start({1});
  // Present position (56) is read-only: Feetech firmware answers with its plain status byte.
  const BusResult result = transact(*engine_, WriteOp{1, 56, {0x00, 0x01}});
  EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(simulator_->read_memory(1, 56, 2), (protocol::Bytes{0x00, 0x08}));
}

TEST_F(BusEngineTest, ReadingThroughTheD55dProtocolUsesTheSameEngine) {
  start({1, 2}, TableId::D55d, 115'200);
  // d55d identity: vendor code 0x5D at 0, software version 1 at 2, ID at 3.
  const BusResult identity = transact(*engine_, ReadOp{2, 0, 4}, Priority::ClientRead);
  ASSERT_EQ(identity.status, BusStatus::Ok) << identity.detail;
  EXPECT_EQ(identity.data[0], 0x5D);
  EXPECT_EQ(identity.data[2], 0x01);
  EXPECT_EQ(identity.data[3], 0x02);

  // Goal position 90 (degrees x resolution 10 = 900 = 0x0384) at 30, low byte first.
  const BusResult write = transact(*engine_, WriteOp{1, 30, {0x84, 0x03}});
  ASSERT_EQ(write.status, BusStatus::Ok) << write.detail;
  EXPECT_EQ(memory(1, 30, 2), (Bytes{0x84, 0x03}));
}

TEST_F(BusEngineTest, D55dInstructionErrorBitIsARefusal) {
  start({1}, TableId::D55d, 115'200);
  // Present position (36) is read-only: the d55d firmware answers with bit 5 (instruction).
  const BusResult result = transact(*engine_, WriteOp{1, 36, {0x01, 0x00}});
  EXPECT_EQ(result.status, BusStatus::ServoRefused) << result.detail;
  EXPECT_EQ(result.servo_error & 0x20, 0x20);
}

// --- timeouts, retries, damaged and late replies -------------------------------------------------

TEST_F(BusEngineTest, SilentServoTimesOutAfterEveryRetry) {
  start({1, 2});
  simulator_->set_offline(2, true);
  const auto started = std::chrono::steady_clock::now();
  const BusResult result = transact(*engine_, ReadOp{2, 56, 2}, Priority::ClientRead);
  const auto elapsed = std::chrono::steady_clock::now() - started;
  EXPECT_EQ(result.status, BusStatus::Timeout);
  EXPECT_NE(result.detail.find("no answer to READ 56+2 of servo 2 after 3 attempts"), std::string::npos)
      << result.detail;
  // Three attempts of 50 ms response timeout plus wire time each.
  EXPECT_GE(elapsed, 150ms);
  EXPECT_LT(elapsed, 2s);
  const auto counters = engine_->counters();
  EXPECT_EQ(counters.timeouts, 3U);
  EXPECT_EQ(counters.retries, 2U);
  EXPECT_EQ(engine_->cache().state(2)->counters.timeouts, 3U);
  EXPECT_EQ(engine_->cache().state(1)->counters.timeouts, 0U);
}

TEST_F(BusEngineTest, DroppedReplyIsRetriedAndTheRetrySucceeds) {
  start({1});
  // The first attempt goes unanswered, whatever the machine's timing; the retry is answered.
  simulator_->drop_next_replies(1);
  const BusResult result = transact(*engine_, ReadOp{1, 5, 1});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x01}));
  EXPECT_GE(engine_->counters().retries, 1U);
}

TEST_F(BusEngineTest, DamagedReplyIsSkippedAndTheRetryIsTaken) {
  start({1});
  simulator_->corrupt_next_replies(1);
  const BusResult result = transact(*engine_, ReadOp{1, 56, 15}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data.size(), 15U);
  const auto counters = engine_->counters();
  // At least the damaged answer's retry; more only where a loaded machine heard an answer late.
  EXPECT_GE(counters.retries, 1U);
  EXPECT_LE(counters.retries, settings_.retries);
  EXPECT_GE(counters.checksum_errors + counters.discarded_bytes, 1U);
  EXPECT_EQ(simulator_->stats().corrupted, 1U);
}

TEST_F(BusEngineTest, RepliesDamagedOnEveryAttemptEndCorruptNotTimeout) {
  start({1});
  simulator_->set_corrupt_probability(1.0);
  const BusResult result = transact(*engine_, ReadOp{1, 56, 15}, Priority::ClientRead);
  EXPECT_EQ(result.status, BusStatus::Corrupt) << result.detail;
  EXPECT_NE(result.detail.find("only damaged answers"), std::string::npos) << result.detail;
  EXPECT_EQ(simulator_->stats().corrupted, 3U);
  EXPECT_GE(engine_->counters().checksum_errors, 1U);
}

TEST_F(BusEngineTest, DecoderResynchronisesAfterGarbageOnTheLine) {
  start({1});
  simulator_->set_corrupt_probability(0.5);
  // Whatever the dice do to individual replies, every READ ends with the right bytes or an
  // honest failure, never with another servo's or a damaged frame's bytes.
  int ok = 0;
  for (int i = 0; i < 20; ++i) {
    const BusResult result = transact(*engine_, ReadOp{1, 3, 3}, Priority::ClientRead);
    if (result.status == BusStatus::Ok) {
      EXPECT_EQ(result.data, (Bytes{0x08, 0x2A, 0x01}));
      ++ok;
    } else {
      EXPECT_TRUE(result.status == BusStatus::Corrupt || result.status == BusStatus::Timeout) << result.detail;
    }
  }
  EXPECT_GE(ok, 15);
}

// A servo that answers late on a bus polled once an hour: offline for answering late, it is
// probed again within the probe period, not after a poll period (a loaded machine that held the
// simulator at start once left such a servo offline for the hour).
class LateServoOnAQuietBus : public BusEngineTest {
  void tweak(BusSettings& settings) override {
    settings.poll = true;
    settings.poll_period = 3600s;
    settings.probe_period = 100ms;
    settings.response_timeout = 30ms;
    settings.retries = 0;
  }
};

TEST_F(LateServoOnAQuietBus, IsProbedAgainWithinTheProbePeriodNotAfterAPollPeriod) {
  start({1});
  ASSERT_TRUE(eventually([&] { return engine_->cache().state(1) && engine_->cache().state(1)->has_data; }))
      << "the start's one poll";
  simulator_->set_reply_delay(1, 60ms);  // past each 30 ms attempt: heard late in the next transaction
  ASSERT_TRUE(eventually(
      [&] {
        (void)transact(*engine_, ReadOp{1, 5, 1}, Priority::ClientRead);
        const auto state = engine_->cache().state(1);
        return state && !state->online && state->offline_reason == OfflineReason::AnswersLate;
      },
      "servo 1 offline for answering late"));
  simulator_->set_reply_delay(1, 0ms);
  EXPECT_TRUE(eventually([&] { return engine_->cache().state(1)->online; }, "servo 1 online again, probed"));
}

class LateReplyTest : public BusEngineTest {
  void tweak(BusSettings& settings) override {
    settings.response_timeout = 100ms;
    settings.retries = 0;
  }
};

TEST_F(LateReplyTest, LateReplyFromAnotherServoIsNotTakenAsTheAnswer) {
  start({1, 2});
  // Servo 2 answers 150 ms late: after the host gave up on it (100 ms) and while it waits for
  // servo 1, which itself answers 75 ms late (inside its 100 ms timeout). Same address and
  // length, so only the reply's ID tells them apart.
  simulator_->set_reply_delay(2, 150ms);
  simulator_->set_reply_delay(1, 75ms);
  const BusResult from_two = transact(*engine_, ReadOp{2, 5, 1}, Priority::ClientRead);
  EXPECT_EQ(from_two.status, BusStatus::Timeout);
  const BusResult from_one = transact(*engine_, ReadOp{1, 5, 1}, Priority::ClientRead);
  ASSERT_EQ(from_one.status, BusStatus::Ok) << from_one.detail;
  EXPECT_EQ(from_one.data, (Bytes{0x01}));
  EXPECT_EQ(engine_->counters().stray_frames, 1U);
}

// --- queue order and back-pressure -----------------------------------------------------------------

class QueueTest : public BusEngineTest {
  void tweak(BusSettings& settings) override {
    settings.response_timeout = 100ms;
    settings.queue_depth = 8;
  }
};

// Everything queued behind a 50 ms operation has waited past its age limit when the bus is free
// again (the picking rule, job_queue.h): the oldest goes first, so nothing starves; each
// priority's own order (a connection's writes) is kept. The strict-priority part of the rule is
// covered by the scheduling tests.
TEST_F(QueueTest, WorkThatWaitedPastItsAgeLimitRunsOldestFirstAndEachPriorityInOrder) {
  start({1, 2});
  simulator_->set_reply_delay(2, 50ms);  // the first operation holds the bus while the rest queue
  std::mutex mutex;
  std::vector<std::string> order;
  std::atomic<int> done{0};
  auto record = [&](std::string name) {
    return [&, name](BusResult result) {
      EXPECT_EQ(result.status, BusStatus::Ok) << name << ": " << result.detail;
      std::lock_guard lock(mutex);
      order.push_back(name);
      ++done;
    };
  };
  // The expected order is the submission order, recorded as the work is submitted: mixed
  // priorities, lowest first, so strict priority alone would give another order.
  std::vector<std::string> submitted;
  auto submit = [&](BusOp op, Priority priority, std::string name) {
    submitted.push_back(name);
    engine_->submit(std::move(op), priority, record(std::move(name)));
  };
  submit(ReadOp{2, 5, 1}, Priority::ClientRead, "slow");
  ASSERT_TRUE(eventually([&] { return simulator_->stats().requests >= 1; }));
  submit(ReadOp{1, 5, 1}, Priority::Poll, "poll-1");
  submit(ReadOp{1, 5, 1}, Priority::Poll, "poll-2");
  submit(ReadOp{1, 5, 1}, Priority::ClientRead, "read-1");
  submit(ReadOp{1, 5, 1}, Priority::Poll, "poll-3");
  submit(ReadOp{1, 5, 1}, Priority::ClientRead, "read-2");
  submit(WriteOp{1, 41, {0x01}}, Priority::ClientWrite, "write-1");
  submit(WriteOp{1, 41, {0x02}}, Priority::ClientWrite, "write-2");
  ASSERT_TRUE(eventually([&] { return done.load() == static_cast<int>(submitted.size()); }));
  std::lock_guard lock(mutex);
  EXPECT_EQ(order, submitted);
  EXPECT_EQ(memory(1, 41, 1), (Bytes{0x02}));  // the writes kept their order
}

TEST_F(QueueTest, FullQueueAnswersQueueFullAtOnce) {
  start({1, 2});
  simulator_->set_reply_delay(2, 50ms);
  std::atomic<int> ok{0};
  engine_->submit(ReadOp{2, 5, 1}, Priority::ClientRead, [&](BusResult) { ++ok; });
  ASSERT_TRUE(eventually([&] { return simulator_->stats().requests >= 1; }));
  for (int i = 0; i < 8; ++i) {
    engine_->submit(ReadOp{1, 5, 1}, Priority::ClientRead, [&](BusResult result) {
      EXPECT_EQ(result.status, BusStatus::Ok) << result.detail;
      ++ok;
    });
  }
  bool refused_inside_submit = false;
  BusResult refused;
  engine_->submit(WriteOp{1, 41, {0x01}}, Priority::ClientWrite, [&](BusResult result) {
    refused = std::move(result);
    refused_inside_submit = true;
  });
  EXPECT_TRUE(refused_inside_submit);
  EXPECT_EQ(refused.status, BusStatus::QueueFull);
  EXPECT_NE(refused.detail.find("8 operations already queued"), std::string::npos) << refused.detail;
  ASSERT_TRUE(eventually([&] { return ok.load() == 9; }));
  EXPECT_EQ(engine_->counters().queue_full, 1U);
  // Room again once the queue drained.
  EXPECT_EQ(transact(*engine_, ReadOp{1, 5, 1}).status, BusStatus::Ok);
}

TEST_F(BusEngineTest, OperationsTheBusCannotExpressAreRejectedAtSubmit) {
  start({1});
  auto ignore = [](BusResult) {};
  EXPECT_THROW(engine_->submit(RawPduOp{1, {0x03, 0x00, 0x00, 0x00, 0x01}}, Priority::ClientRead, ignore),
               std::invalid_argument);
  EXPECT_THROW(engine_->submit(ReadOp{254, 5, 1}, Priority::ClientRead, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(ReadOp{1, 5, 0}, Priority::ClientRead, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(ReadOp{1, 300, 1}, Priority::ClientRead, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(WriteOp{1, 42, {}}, Priority::ClientWrite, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(SyncWriteOp{42, 2, {{1, {0x01}}}}, Priority::ClientWrite, ignore),
               std::invalid_argument);
}

TEST_F(BusEngineTest, StopCancelsWhatIsQueued) {
  start({1, 2});
  simulator_->set_reply_delay(2, 30ms);
  std::atomic<bool> on_the_wire{false};
  simulator_->set_frame_observer([&](const simulator::ReceivedFrame&) { on_the_wire = true; });
  std::vector<BusStatus> statuses;
  std::mutex mutex;
  for (int i = 0; i < 4; ++i) {
    engine_->submit(ReadOp{2, 5, 1}, Priority::ClientRead, [&](BusResult result) {
      std::lock_guard lock(mutex);
      statuses.push_back(result.status);
    });
  }
  ASSERT_TRUE(eventually([&] { return on_the_wire.load(); }));  // the first READ is on the wire
  engine_->stop();
  simulator_->set_frame_observer({});
  std::lock_guard lock(mutex);
  ASSERT_EQ(statuses.size(), 4U);  // every completion ran, none was lost
  // The transaction on the wire when stop() came ends with its own result (a write on the wire
  // may have been carried out: it is not reported cancelled); the three still queued are Cancelled.
  EXPECT_NE(statuses.front(), BusStatus::Cancelled);
  EXPECT_EQ(std::count(statuses.begin(), statuses.end(), BusStatus::Cancelled), 3);
  bool after_stop = false;
  engine_->submit(ReadOp{1, 5, 1}, Priority::ClientRead,
                  [&](BusResult result) { after_stop = result.status == BusStatus::Cancelled; });
  EXPECT_TRUE(after_stop);
}

// --- bit rates ---------------------------------------------------------------------------------------

TEST_F(BusEngineTest, RunsAt76800Baud) {
  start({1}, TableId::Sts, 76'800);  // feetech baud code 5
  const BusResult result = transact(*engine_, ReadOp{1, 6, 1}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x05}));
}

TEST_F(BusEngineTest, RunsAt128000Baud) {
  start({1}, TableId::Sts, 128'000);  // feetech baud code 3
  const BusResult result = transact(*engine_, ReadOp{1, 6, 1}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x03}));
}

TEST_F(BusEngineTest, ServoAtAnotherRateDoesNotAnswer) {
  start({1}, TableId::Sts, 76'800, 115'200);
  const BusResult result = transact(*engine_, ReadOp{1, 6, 1}, Priority::ClientRead);
  EXPECT_EQ(result.status, BusStatus::Timeout) << result.detail;
}

}  // namespace
}  // namespace sms::gateway
