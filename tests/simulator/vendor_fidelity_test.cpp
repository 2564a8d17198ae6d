// The servo behaviours checked against Feetech's own SDKs and wiki (docs/DECISIONS.md "Vendor
// fidelity"), driven through the simulator's pty with frames written out byte by byte here —
// not with the project's codecs, so a regression in either the simulator or protocol/ shows
// without the vendor SDK.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <numeric>
#include <thread>

#include "modbus_map/status_bits.h"
#include "modbus_map/tables.h"
#include "simulator/table_behaviour.h"
#include "simulator/virtual_servo.h"
#include "tests/simulator/sim_fixture.h"

namespace sms::simulator::testing {
namespace {

using namespace std::chrono_literals;

constexpr std::uint8_t kPing = 0x01;
constexpr std::uint8_t kRead = 0x02;
constexpr std::uint8_t kWrite = 0x03;
constexpr std::uint8_t kRegWrite = 0x04;
constexpr std::uint8_t kAction = 0x05;
constexpr std::uint8_t kBroadcast = 0xFE;

// FF FF ID LEN INSTR P... CHK, CHK = ~(ID + LEN + INSTR + P...) (docs/PROTOCOL.md §1.1), spelled out here.
Bytes frame(std::uint8_t id, std::uint8_t instruction, const Bytes& params = {}) {
  // Built by push_back into reserved room: GCC 12 at -O3 takes an insert after a 5-byte
  // initializer list for a write out of bounds (-Warray-bounds), a false positive.
  Bytes bytes;
  bytes.reserve(params.size() + 6);
  for (const std::uint8_t byte :
       {std::uint8_t{0xFF}, std::uint8_t{0xFF}, id, static_cast<std::uint8_t>(params.size() + 2), instruction}) {
    bytes.push_back(byte);
  }
  for (const std::uint8_t param : params) bytes.push_back(param);
  const unsigned sum = std::accumulate(bytes.begin() + 2, bytes.end(), 0U);
  bytes.push_back(static_cast<std::uint8_t>(~sum & 0xFF));
  return bytes;
}
// The status frame a servo sends back: FF FF ID LEN ERROR P... CHK.
Bytes status_frame(std::uint8_t id, std::uint8_t error, const Bytes& params = {}) { return frame(id, error, params); }

class VendorFidelity : public ::testing::Test {
 protected:
  void start(std::vector<ServoConfig> servos) { rig = std::make_unique<Rig>(quick_options(std::move(servos))); }
  Bytes exchange(const Bytes& request, std::size_t reply_params) {
    rig->host->send(request);
    return rig->host->receive_exactly(6 + reply_params);
  }
  // The data bytes of a READ, or empty when the answer is not the expected status frame.
  Bytes read(std::uint8_t id, std::uint8_t address, std::uint8_t count) {
    const Bytes reply = exchange(frame(id, kRead, {address, count}), count);
    if (reply.size() != 6U + count || reply[4] != 0) return {};
    return Bytes(reply.begin() + 5, reply.end() - 1);
  }
  void write(std::uint8_t id, std::uint8_t address, Bytes data) {
    data.insert(data.begin(), address);
    ASSERT_EQ(exchange(frame(id, kWrite, data), 0), status_frame(id, 0)) << "WRITE " << int(address);
  }
  std::unique_ptr<Rig> rig;
};

ServoConfig scs(std::uint8_t id) { return {id, modbus_map::TableId::Scs, protocol::BusProtocol::Feetech, 1'000'000}; }

// --- REG WRITE flag (address 64: wiki memory-sts "Async Write Flag", SMSCL SDK) -----------------

TEST_F(VendorFidelity, RegWriteFlagIsSetUntilAction) {
  start({sts(1), scs(2)});
  for (const std::uint8_t id : {1, 2}) {
    EXPECT_EQ(read(id, 64, 1), Bytes{0}) << "servo " << int(id);
    // REG WRITE goal 1000 (low first on sts, high first on scs).
    const Bytes goal = id == 1 ? Bytes{42, 0xE8, 0x03} : Bytes{42, 0x03, 0xE8};
    ASSERT_EQ(exchange(frame(id, kRegWrite, goal), 0), status_frame(id, 0));
    EXPECT_EQ(read(id, 64, 1), Bytes{1}) << "servo " << int(id) << ": REG WRITE pending";
  }
  rig->host->send(frame(kBroadcast, kAction));  // no answer to a broadcast
  std::this_thread::sleep_for(20ms);
  EXPECT_EQ(read(1, 64, 1), Bytes{0});
  EXPECT_EQ(read(2, 64, 1), Bytes{0});
  EXPECT_EQ(read(1, 42, 2), (Bytes{0xE8, 0x03}));
  EXPECT_EQ(read(2, 42, 2), (Bytes{0x03, 0xE8}));
}

TEST_F(VendorFidelity, PresentGoalShowsTheGoalTheServoDrivesTo) {
  start({sts(1)});
  write(1, 42, {0xC4, 0x09});  // goal 2500
  EXPECT_EQ(read(1, 67, 2), (Bytes{0xC4, 0x09}));
}

// --- torque switch 40 = 2: damping (wiki memory-sts); power-on value 0 -----------------------

TEST_F(VendorFidelity, TorqueSwitchPowersOnOffAndAcceptsDamping) {
  start({sts(1), scs(2)});
  for (const std::uint8_t id : {1, 2}) {
    EXPECT_EQ(read(id, 40, 1), Bytes{0}) << "servo " << int(id) << ": torque off at power-on";
    write(id, 40, {2});
    EXPECT_EQ(read(id, 40, 1), Bytes{2}) << "servo " << int(id) << ": damping accepted";
    EXPECT_EQ(read(id, 66, 1), Bytes{0}) << "servo " << int(id) << ": damping does not drive the motor";
  }
  write(1, 42, {0x00, 0x0A});  // a goal lifts damping like torque off: the torque comes on
  EXPECT_EQ(read(1, 40, 1), Bytes{1});
}

// --- status bit 4 unused: a refused write is not flagged, nothing lands -----------------------

TEST_F(VendorFidelity, WriteToReadOnlyFieldIsIgnoredWithoutAnErrorBit) {
  start({sts(1)});
  const Bytes before = read(1, 56, 2);
  EXPECT_EQ(exchange(frame(1, kWrite, {56, 0x00, 0x04}), 0), status_frame(1, 0));
  EXPECT_EQ(read(1, 56, 2), before);
  EXPECT_EQ(read(1, 65, 1), Bytes{0});
}

TEST_F(VendorFidelity, OutOfRangeValueKeepsTheFieldAndLetsTheRestLand) {
  start({sts(1)});
  // response level 7 (max 1) and max temperature 80 in one write: only the temperature lands.
  EXPECT_EQ(exchange(frame(1, kWrite, {8, 7}), 0), status_frame(1, 0));
  EXPECT_EQ(read(1, 8, 1), Bytes{1});
  EXPECT_EQ(exchange(frame(1, kWrite, {13, 80}), 0), status_frame(1, 0));
  EXPECT_EQ(read(1, 13, 1), Bytes{80});
}

// --- speed unit by phase bit 2 (wiki memory-sts; FTServo_Python sms_sts/write.py) -------------

TEST_F(VendorFidelity, VendorWritePosExReachesItsGoalInTheVendorsWait) {
  start({sts(1)});
  // WritePosEx(1, 4095, 60, 50): 7 bytes from 41 = ACC, position, time 0, speed (low first).
  write(1, 41, {50, 0xFF, 0x0F, 0x00, 0x00, 60, 0x00});
  // The example then sleeps (4095-0)/(60*50) + (60*50)/(50*100) + 0.05 ≈ 2.0 s from position 0;
  // from 2048 the servo is there well within that at 60 × 0.732 rpm ≈ 3000 steps/s.
  EXPECT_TRUE(eventually([&] { return read(1, 56, 2) == Bytes{0xFF, 0x0F}; })) << hex(read(1, 56, 2));
}

TEST_F(VendorFidelity, PhaseBit2SwitchesTheSpeedUnitToStepsPerSecond) {
  start({sts(1)});
  write(1, 18, {0x04});
  write(1, 41, {0, 0xFF, 0x0F, 0x00, 0x00, 60, 0x00});  // 60 steps/s now
  std::this_thread::sleep_for(500ms);
  const Bytes position = read(1, 56, 2);
  ASSERT_EQ(position.size(), 2U);
  const int present = position[0] | position[1] << 8;
  EXPECT_GT(present, 2048);
  EXPECT_LT(present, 2048 + 60) << "half a second at 60 steps/s";
  // The present speed reads in the same unit.
  const Bytes speed = read(1, 58, 2);
  ASSERT_EQ(speed.size(), 2U);
  EXPECT_NEAR(speed[0] | speed[1] << 8, 60, 2);
}

// --- return delay floor: below 50 acts as 50 = 100 µs (wiki memory-sts address 7) ------------

TEST(VendorReturnDelay, StsValuesBelowFiftyActAsFifty) {
  const auto now = Clock::now();
  VirtualServo servo(sts(1), now, 100ms);
  EXPECT_EQ(servo.memory().raw(*modbus_map::field_by_name(servo.table(), "return_delay")), 0U) << "factory value";
  EXPECT_EQ(std::chrono::duration_cast<std::chrono::microseconds>(servo.return_delay()), 100us);
  const Bytes delay_10{10};
  servo.write_raw(7, delay_10, now);
  EXPECT_EQ(std::chrono::duration_cast<std::chrono::microseconds>(servo.return_delay()), 100us);
  const Bytes delay_200{200};
  servo.write_raw(7, delay_200, now);
  EXPECT_EQ(std::chrono::duration_cast<std::chrono::microseconds>(servo.return_delay()), 400us);
}

TEST_F(VendorFidelity, ReturnDelayFloorShowsOnTheWire) {
  BusOptions options = quick_options({sts(1)});
  options.timing = true;
  rig = std::make_unique<Rig>(options);
  // PING out (6 bytes, 60 µs at 1 Mbaud), 100 µs floor, PING answer back (60 µs): never faster.
  std::chrono::steady_clock::duration fastest = 1s;
  for (int i = 0; i < 5; ++i) {
    const auto sent = std::chrono::steady_clock::now();
    ASSERT_EQ(exchange(frame(1, kPing), 0), status_frame(1, 0));
    fastest = std::min(fastest, std::chrono::steady_clock::now() - sent);
  }
  EXPECT_GE(fastest, 220us);
}

// --- SCS: high byte first, lock at 48, byte-order flag at 2 (SCSCL SDK, End = 1) --------------

TEST_F(VendorFidelity, ScsServoSpeaksHighByteFirst) {
  start({scs(1)});
  EXPECT_EQ(read(1, 2, 1), Bytes{1}) << "byte-order flag";
  EXPECT_EQ(read(1, 56, 2), (Bytes{0x02, 0x00})) << "present position 512, high byte first";
  EXPECT_EQ(read(1, 11, 2), (Bytes{0x03, 0xFF})) << "max angle limit 1023";
  // SCSCL WritePos(1, 1000, 0, 1500): goal, time, speed from 42, high byte first.
  write(1, 42, {0x03, 0xE8, 0x00, 0x00, 0x05, 0xDC});
  EXPECT_TRUE(eventually([&] { return read(1, 56, 2) == Bytes{0x03, 0xE8}; })) << hex(read(1, 56, 2));
  EXPECT_EQ(read(1, 40, 1), Bytes{1}) << "the goal switched the torque on";
}

TEST_F(VendorFidelity, ScsLockIsAddress48) {
  start({scs(1)});
  EXPECT_EQ(read(1, 48, 1), Bytes{1});
  write(1, 48, {0});
  EXPECT_EQ(read(1, 48, 1), Bytes{0});
}

TEST_F(VendorFidelity, ScsBothLimitsZeroIsTheOpenLoopMotor) {
  start({scs(1)});
  write(1, 40, {1});
  write(1, 9, {0x00, 0x00, 0x00, 0x00});  // SCSCL PWMMode
  write(1, 44, {0x05, 0xF4});             // WritePWM(1, -500): bit 10 direction, high first
  EXPECT_TRUE(eventually([&] {
    const Bytes speed = read(1, 58, 2);
    return speed.size() == 2 && (speed[0] & 0x80) != 0;  // turning backwards
  }));
}

TEST_F(VendorFidelity, ScsHasNoSyncRead) {
  start({scs(1)});
  rig->host->send(frame(kBroadcast, 0x82, {56, 2, 1}));
  EXPECT_TRUE(rig->host->receive(30ms, 200ms).empty());
}

// --- sms1: 41 acceleration, written by the SMSCL SDK's 7-byte WritePosEx ----------------------

TEST_F(VendorFidelity, Sms1TakesTheSmsclSevenByteWrite) {
  start({sms1(1)});
  write(1, 41, {20, 0x00, 0x0C, 0x00, 0x00, 0x00, 0x00});  // ACC 20, goal 3072, time 0, speed 0
  EXPECT_EQ(read(1, 41, 1), Bytes{20});
  EXPECT_EQ(read(1, 42, 2), (Bytes{0x00, 0x0C}));
}

// --- status bits: the gateway's names (TableSpec::status_bits) for the bits the firmware reports --

TEST(VendorStatusBits, EveryTableNamesEachBitItsServosReportAndCallsTorqueOnNoFault) {
  for (const modbus_map::TableSpec* spec : modbus_map::all_tables()) {
    std::uint8_t faults = 0;
    std::uint8_t states = 0;
    for (const modbus_map::StatusBit& bit : spec->status_bits) (bit.fault ? faults : states) |= bit.mask;
    EXPECT_EQ(faults, behaviour(spec->id).error_mask) << spec->name << ": the fault bits its firmware reports";
    EXPECT_EQ(states, behaviour(spec->id).torque_on_status_bit) << spec->name << ": the bits that are states";
  }
}

TEST_F(VendorFidelity, SmsmbWithTorqueOnShowsBitFourAndNoFault) {
  start({smsmb(1)});
  ASSERT_TRUE(rig->bus->write_memory(1, 0x81, Bytes{0x00, 0x01}));  // torque on
  const auto status = rig->bus->read_field(1, "status");
  ASSERT_TRUE(status);
  EXPECT_EQ(*status, 0x10);
  EXPECT_TRUE(modbus_map::status_faults(modbus_map::TableId::Smsmb, static_cast<std::uint8_t>(*status)).empty());
  rig->bus->set_error_bits(1, 0x01);  // over-voltage
  const auto faulty = rig->bus->read_field(1, "status");
  ASSERT_TRUE(faulty);
  EXPECT_EQ(*faulty, 0x11);
  EXPECT_EQ(modbus_map::status_faults(modbus_map::TableId::Smsmb, static_cast<std::uint8_t>(*faulty)),
            std::vector<std::string>{"voltage"});
}

}  // namespace
}  // namespace sms::simulator::testing
