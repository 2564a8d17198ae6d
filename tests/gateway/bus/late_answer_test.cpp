// Late answers (transactor.h "Late answers", docs/DECISIONS.md): a servo's answer names no
// request, so one that comes after its request gave up looks exactly like the answer to the
// next request of the same size. Both transactors, against the simulator's late servo, read two
// constant blocks of the same size in turn: whatever the lateness (just past one attempt to many
// times a whole transaction), an answer taken as Ok always carries its own block, never the
// other one; once the lateness ends, answers come back; what was dropped is counted (stray
// frames, fences sent).
#include <gtest/gtest.h>

#include <chrono>
#include <iostream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gateway/bus/packet_transactor.h"
#include "gateway/bus/rtu_transactor.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway::testing {
namespace {

using namespace std::chrono_literals;

constexpr std::uint8_t kServo = 1;
constexpr unsigned kAttempts = 3;
constexpr auto kAllowance = 25ms;

struct Reads {
  AddressBlock block;
  protocol::Bytes expected;
};

// Alternates reads of `a` and `b` while the servo answers `lateness` late, then on time again.
template <typename Transactor>
void never_taken_for_another_answer(Transactor& transactor, simulator::SimulatedBus& bus, const Reads& a,
                                    const Reads& b, BusCounters& counters) {
  ASSERT_NE(a.expected, b.expected) << "the two blocks must differ for a mix-up to show";
  TransactionEvents events;
  unsigned wrong = 0;
  unsigned late_ok = 0;
  const auto read = [&](const Reads& reads, const std::string& when) {
    const BusResult result = transactor.execute(transactor.read_request(kServo, reads.block, kAttempts), events);
    if (result.status != BusStatus::Ok) return false;
    EXPECT_EQ(result.data, reads.expected) << when << ": the answer to another request was taken for this one";
    if (result.data != reads.expected) ++wrong;
    return result.data == reads.expected;
  };
  // From just past one attempt's timeout (about 27 ms) to five whole transactions.
  for (const auto lateness : {30ms, 50ms, 90ms, 150ms, 400ms}) {
    bus.set_reply_delay(kServo, lateness);
    for (int i = 0; i < 8; ++i) {
      const std::string when = "late " + std::to_string(lateness.count()) + " ms, read " + std::to_string(i);
      if (read(i % 2 == 0 ? a : b, when)) ++late_ok;
    }
  }
  bus.set_reply_delay(kServo, 0ms);
  // On time again: the owed answers come (dropped), a fence is answered, then every read is.
  unsigned in_a_row = 0;
  for (int i = 0; i < 40 && in_a_row < 6; ++i) {
    in_a_row = read(i % 2 == 0 ? a : b, "on time, read " + std::to_string(i)) ? in_a_row + 1 : 0;
  }
  EXPECT_EQ(wrong, 0U);
  EXPECT_EQ(in_a_row, 6U) << "reads were not answered again once the servo was on time";
  const auto snapshot = counters.snapshot();
  EXPECT_GT(snapshot.stray_frames + snapshot.stray_bytes, 0U) << "the late answers were not counted as stray";
  EXPECT_GT(snapshot.fences, 0U) << "no fence went before a read whose answer an owed one could look like";
  EXPECT_GT(snapshot.timeouts, 0U);
  // Informative: a late answer to an earlier attempt of the same request is its answer.
  std::cout << "late reads answered with their own data: " << late_ok << ", stray bytes " << snapshot.stray_bytes
            << ", stray frames " << snapshot.stray_frames << ", fences " << snapshot.fences << "\n";
}

simulator::BusOptions one_servo(modbus_map::TableId table, std::uint32_t baud) {
  simulator::BusOptions options = simulated_servos({kServo}, table, baud);
  options.timing = false;  // the lateness is the fault alone
  return options;
}

// OwedAnswers alone (transactor.h): which requests need a fence, which length it takes, what its
// answer settles.
AnswerShape params(std::initializer_list<std::size_t> counts) { return AnswerShape::of(0, counts); }

TEST(OwedAnswers, ARequestCollidesOnlyWithOwedAnswersItCouldTakeForItsOwn) {
  OwedAnswers owed;
  EXPECT_FALSE(owed.owes(1));
  owed.add(1, params({4, 0}), 1);  // a 4-byte read that went unanswered (or was refused)
  EXPECT_TRUE(owed.collides(1, params({4, 0})));
  EXPECT_TRUE(owed.collides(1, params({0})));      // a write's acknowledgement looks like its refusal
  EXPECT_FALSE(owed.collides(1, params({15})));    // a SYNC READ member's 15 bytes do not
  EXPECT_FALSE(owed.collides(2, params({4, 0})));  // another servo's answers name it
  // RTU: the function code tells answers apart, then the length.
  owed.add(3, AnswerShape::of(0x03, {10, AnswerShape::kExceptionLength}), 1);
  EXPECT_FALSE(owed.collides(3, AnswerShape::of(0x06, {5, AnswerShape::kExceptionLength})));
  EXPECT_TRUE(owed.collides(3, AnswerShape::of(0x03, {6, AnswerShape::kExceptionLength})));  // its exception
  EXPECT_FALSE(owed.collides(3, AnswerShape::of(0x03, {6})));                                // a fence
}

TEST(OwedAnswers, FencesShareALengthWhileUnansweredAndTheListStaysShort) {
  OwedAnswers owed;
  const auto fence = [](unsigned units) { return AnswerShape::of(0, {units}); };
  constexpr unsigned kLongest = 4;
  owed.add(1, params({1, 0}), 1);  // a 1-byte read went unanswered
  // The next 1-byte read needs a fence; length 1 is owed, and would be its own answer.
  ASSERT_EQ(owed.fence_length(1, fence, params({1, 0}), kLongest), 2U);
  owed.add(1, fence(2), 1, 2);  // that fence went unanswered too
  // The next one shares its length: whichever of them answers, the read before them has come.
  ASSERT_EQ(owed.fence_length(1, fence, params({1, 0}), kLongest), 2U);
  // A silent servo: blind stops and fences one after another; the list does not grow.
  for (int period = 0; period < 20; ++period) {
    owed.add(1, params({0}), 1);
    owed.add(1, fence(2), 1, 2);
  }
  EXPECT_EQ(owed.count(1), 1U + 21U + 20U);
  // Before a write: a fence of 2 would leave the blind stops' acknowledgements after it, so a
  // length nobody owes is taken.
  ASSERT_EQ(owed.fence_length(1, fence, params({0}), kLongest), 3U);
  // A fence of 2 answered (maybe the first one's late answer): what came before the first fence
  // of 2 is settled, what came after it may still come.
  owed.fence_answered(1, 2);
  EXPECT_FALSE(owed.collides(1, params({1})));
  EXPECT_TRUE(owed.collides(1, params({0})));
  EXPECT_TRUE(owed.collides(1, fence(2)));
  // A fence of a length nobody owes answered: everything before it settles.
  owed.fence_answered(1, 3);
  EXPECT_FALSE(owed.owes(1));
  // An answer only the latest request could give settles everything too.
  owed.add(1, params({4, 0}), 2);
  owed.settled(1);
  EXPECT_FALSE(owed.owes(1));
}

TEST(OwedAnswers, NoFenceWhenEveryLengthIsOwedByAnotherRequest) {
  OwedAnswers owed;
  const auto fence = [](unsigned units) { return AnswerShape::of(0, {units}); };
  for (std::size_t length = 1; length <= 4; ++length) owed.add(1, params({length, 0}), 1);
  EXPECT_EQ(owed.fence_length(1, fence, params({0}), 4), std::nullopt);
  EXPECT_EQ(owed.fence_length(1, fence, params({0}), 5), 5U);
}

TEST(OwedAnswers, AStrayFrameIsTheOldestOwedAnswerItCanBe) {
  OwedAnswers owed;
  owed.add(1, params({4, 0}), 2);
  owed.add(1, params({15}), 1);
  EXPECT_FALSE(owed.arrived(1, AnswerShape::frame(0, 7)));  // nobody asked for 7 bytes: noise, counted as stray
  EXPECT_TRUE(owed.arrived(1, AnswerShape::frame(0, 4)));
  EXPECT_EQ(owed.count(1), 2U);
  EXPECT_TRUE(owed.arrived(1, AnswerShape::frame(0, 15)));
  EXPECT_TRUE(owed.arrived(1, AnswerShape::frame(0, 0)));  // the other read, refused late
  EXPECT_FALSE(owed.owes(1));
}

// A late answer is one a request waited for and gave up on: it says since when it waited. The
// answer to a frame sent blind (an owed stop's first try) is owed too, but nobody waited: not late.
TEST(OwedAnswers, AnAnswerIsLateOnlyWhereARequestWaitedForIt) {
  OwedAnswers owed;
  const auto asked = SteadyClock::now() - std::chrono::milliseconds{50};
  owed.add(1, params({4, 0}), 1, 0, asked);
  owed.add(1, params({0}), 1, 0, std::nullopt);  // a write sent blind
  const auto read = owed.arrived(1, AnswerShape::frame(0, 4));
  ASSERT_TRUE(read);
  EXPECT_EQ(read.late_since, asked);
  const auto blind = owed.arrived(1, AnswerShape::frame(0, 0));
  EXPECT_TRUE(blind);
  EXPECT_FALSE(blind.late_since);
  EXPECT_FALSE(owed.arrived(1, AnswerShape::frame(0, 4)));  // nothing owed any more: noise
  // Entries of one kind keep the latest request's sending: the answer is at least that late.
  owed.add(2, params({4, 0}), 1, 0, asked);
  owed.add(2, params({4, 0}), 1, 0, asked + std::chrono::milliseconds{20});
  EXPECT_EQ(owed.arrived(2, AnswerShape::frame(0, 4)).late_since, asked + std::chrono::milliseconds{20});
}

TEST(LateAnswers, PacketBusNeverTakesALateAnswerForTheNextRequests) {
  simulator::SimulatedBus bus(one_servo(modbus_map::TableId::Sts, 1'000'000));
  bus.start();
  BusCounters counters;
  SerialSettings serial;
  serial.device = bus.slave_path();
  PacketTransactor transactor(protocol::BusProtocol::Feetech, serial, TransactionTiming{kAllowance, "late: "},
                              counters);
  ASSERT_TRUE(transactor.open());
  // sts EEPROM: angle limits (9-12) and temperature/voltage limits, torque (13-16): constant.
  const Reads limits{{9, 4}, *bus.read_memory(kServo, 9, 4)};
  const Reads ratings{{13, 4}, *bus.read_memory(kServo, 13, 4)};
  never_taken_for_another_answer(transactor, bus, limits, ratings, counters);
}

TEST(LateAnswers, RtuBusNeverTakesALateAnswerForTheNextRequests) {
  simulator::SimulatedBus bus(one_servo(modbus_map::TableId::Smsmb, 115'200));
  bus.start();
  BusCounters counters;
  RtuLineSettings line;
  line.serial.device = bus.slave_path();
  line.serial.baud = 115'200;
  RtuTransactor transactor(line, TransactionTiming{kAllowance, "late: "}, counters);
  ASSERT_TRUE(transactor.open());
  // SMSMB EEPROM registers: angle limits (0x0D-0x0E) and position gains (0x11-0x12).
  const Reads limits{{0x0D, 2}, *bus.read_memory(kServo, 0x0D, 2)};
  const Reads gains{{0x11, 2}, *bus.read_memory(kServo, 0x11, 2)};
  never_taken_for_another_answer(transactor, bus, limits, gains, counters);
}

// Before the guard, the late answer of a timed-out request was taken for the next request of
// the same size: the stray bytes the input holds before a request are dropped and counted.
TEST(LateAnswers, BytesWaitingBeforeARequestAreDroppedAndCounted) {
  simulator::SimulatedBus bus(one_servo(modbus_map::TableId::Sts, 1'000'000));
  bus.start();
  BusCounters counters;
  SerialSettings serial;
  serial.device = bus.slave_path();
  PacketTransactor transactor(protocol::BusProtocol::Feetech, serial, TransactionTiming{kAllowance, "late: "},
                              counters);
  ASSERT_TRUE(transactor.open());
  TransactionEvents events;
  // One attempt, answered 40 ms late: it times out.
  bus.set_reply_delay(kServo, 40ms);
  EXPECT_EQ(transactor.execute(transactor.read_request(kServo, {9, 4}, 1), events).status, BusStatus::Timeout);
  bus.set_reply_delay(kServo, 0ms);
  // The late answer is waiting in the input when the next request goes out.
  std::this_thread::sleep_for(80ms);
  const BusResult next = transactor.execute(transactor.read_request(kServo, {13, 4}, 1), events);
  ASSERT_EQ(next.status, BusStatus::Ok) << next.detail;
  EXPECT_EQ(next.data, *bus.read_memory(kServo, 13, 4));
  EXPECT_EQ(counters.snapshot().stray_bytes, 10U) << "the late 10-byte answer (FF FF 01 06 00 + 4 + checksum)";
}

}  // namespace
}  // namespace sms::gateway::testing
