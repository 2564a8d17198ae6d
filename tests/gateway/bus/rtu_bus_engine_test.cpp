// The modbus-rtu bus engine (EngineCore<RtuTransactor>) and RtuMaster against the simulator's
// SMSMB servos on a pty: every rate of the Modbus baud table (libmodbus alone would run 256000,
// 128000, 56000 and 14400 at 9600), FC03 reads, FC06/FC16 writes, broadcast, exceptions,
// retries, polling into the cache, offline and back, a lost port, the frame gap against a slave
// that keeps its own t3.5.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "gateway/bus/engine_core.h"
#include "gateway/bus/rtu_master.h"
#include "gateway/bus/rtu_transactor.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"
#include "tests/support/engine_conformance.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using modbus_map::TableId;
using protocol::BusProtocol;
using protocol::Bytes;
using testing::eventually;
using testing::transact;

constexpr AddressBlock kFeedback{0x100, 8};

simulator::BusOptions smsmb_servos(std::vector<std::uint8_t> ids, std::uint32_t baud = 115'200) {
  simulator::BusOptions options;
  for (const auto id : ids) options.servos.push_back({id, TableId::Smsmb, BusProtocol::ModbusRtu, baud});
  options.seed = 1;
  return options;
}

BusSettings rtu_settings(std::string device, std::vector<std::uint8_t> ids, std::uint32_t baud = 115'200) {
  BusSettings settings;
  settings.name = "rtu";
  settings.protocol = BusProtocol::ModbusRtu;
  settings.serial.device = std::move(device);
  settings.serial.baud = baud;
  // Generous: a pty, the simulator's thread and the sanitizers on 2 shared cores.
  settings.response_timeout = 50ms;
  settings.retries = 2;
  settings.poll_period = 10ms;
  settings.probe_period = 200ms;
  settings.reopen_period = 50ms;
  for (const auto id : ids)
    settings.servos.push_back({id, TableId::Smsmb, modbus_map::ByteOrder::HighFirst, kFeedback});
  return settings;
}

config::ModbusRtuOptions line_options() {
  config::ModbusRtuOptions options;
  options.byte_timeout = 20ms;
  return options;
}

TEST(RtuRates, LibmodbusSetsOnlyItsOwnConstants) {
  EXPECT_TRUE(libmodbus_sets_rate(115'200));
  EXPECT_TRUE(libmodbus_sets_rate(9'600));
  EXPECT_TRUE(libmodbus_sets_rate(1'000'000));
  EXPECT_FALSE(libmodbus_sets_rate(256'000));
  EXPECT_FALSE(libmodbus_sets_rate(128'000));
  EXPECT_FALSE(libmodbus_sets_rate(56'000));
  EXPECT_FALSE(libmodbus_sets_rate(14'400));
}

TEST(RtuRates, FrameGapIsThreeAndAHalfCharactersUpTo19200ThenFixed) {
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 115'200}), 1750us);
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 19'200}), 1'822'917ns);  // 35 bits / 19200 /s, rounded up
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 9'600}), 3'645'833ns);   // 7'291'667 ns halved
  // The configurable gaps: 3.5 characters at every rate, or a fixed time.
  const config::FrameGap characters{config::FrameGap::Kind::Characters, {}};
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 115'200}, characters), 303'819ns);  // 35 bits / 115200 /s
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 19'200}, characters), 1'822'917ns);
  EXPECT_EQ(rtu_frame_gap(SerialSettings{"", 115'200}, config::FrameGap{config::FrameGap::Kind::Fixed, 200us}), 200us);
  EXPECT_EQ(config::parse_frame_gap("3.5chars")->kind, config::FrameGap::Kind::Characters);
  EXPECT_EQ(config::parse_frame_gap("250us")->fixed, 250us);
  EXPECT_FALSE(config::parse_frame_gap("250ms"));
  EXPECT_FALSE(config::parse_frame_gap("2000000us"));
}

// Each rate of the SMSMB baud table (docs/PROTOCOL.md §3 modbus-rtu column): the simulated servo answers
// only when the host's line runs at its rate, so an answer proves the rate was set.
TEST(RtuMaster, ReachesAServoAtEveryRateOfTheModbusTable) {
  for (const std::uint32_t baud :
       {256'000U, 128'000U, 115'200U, 57'600U, 56'000U, 38'400U, 19'200U, 14'400U, 9'600U, 4'800U}) {
    SCOPED_TRACE(baud);
    simulator::SimulatedBus bus(smsmb_servos({1}, baud));
    bus.start();
    RtuMaster master(RtuLineSettings{SerialSettings{bus.slave_path(), baud}, line_options()});
    ASSERT_TRUE(master.open());
    // FC03 of register 0x0A (ID): 03, byte count 2, 00 01.
    const std::vector<std::uint8_t> read_id{0x03, 0x00, 0x0A, 0x00, 0x01};
    const RtuExchange exchange = master.transact(1, read_id, 100ms);
    ASSERT_EQ(exchange.outcome, RtuOutcome::Reply) << exchange.detail;
    EXPECT_EQ(exchange.pdu, (Bytes{0x03, 0x02, 0x00, 0x01}));
  }
}

TEST(RtuMaster, FramesAnAnswerLibmodbusCannotSizeBySilence) {
  // Feetech's restart (0x41) is answered with an echo (simulator decision); libmodbus has no
  // length rule for it, so the answer ends at the silence after it.
  simulator::SimulatedBus bus(smsmb_servos({1}));
  bus.start();
  RtuMaster master(RtuLineSettings{SerialSettings{bus.slave_path(), 115'200}, line_options()});
  ASSERT_TRUE(master.open());
  // The request is slave, 0x41, CRC (protocol/modbus_rtu.cpp's reading of docs/PROTOCOL.md §1.3).
  const std::vector<std::uint8_t> restart{0x41};
  const RtuExchange exchange = master.transact(1, restart, 100ms);
  ASSERT_EQ(exchange.outcome, RtuOutcome::Reply) << exchange.detail;
  EXPECT_EQ(exchange.pdu, (Bytes{0x41}));
}

TEST(RtuMaster, SilentSlaveTimesOut) {
  simulator::SimulatedBus bus(smsmb_servos({1}));
  bus.start();
  RtuMaster master(RtuLineSettings{SerialSettings{bus.slave_path(), 115'200}, line_options()});
  ASSERT_TRUE(master.open());
  const std::vector<std::uint8_t> read_id{0x03, 0x00, 0x0A, 0x00, 0x01};
  EXPECT_EQ(master.transact(9, read_id, 20ms).outcome, RtuOutcome::Timeout);
}

// The frame gap is counted from the last byte on the wire. The simulated SMSMB servo
// keeps its own t3.5 (wire timing on) and ignores a request that follows its answer closer than
// that. At 4800 bit/s 3.5 characters are 7.3 ms, far above what a pty adds, and a transaction's
// frames take 31 ms, so a gap counted from the send instead would be over before the answer.
constexpr std::uint32_t kSlowRtuBaud = 4'800;

RtuLineSettings line_with_gap(const std::string& device, std::string_view gap) {
  RtuLineSettings settings{SerialSettings{device, kSlowRtuBaud}, line_options()};
  settings.options.frame_gap = *config::parse_frame_gap(gap);
  return settings;
}

TEST(RtuMaster, BackToBackTransactionsWithAThreeAndAHalfCharacterGapAreAllAnswered) {
  simulator::SimulatedBus bus(smsmb_servos({1}, kSlowRtuBaud));
  bus.start();
  RtuMaster master(line_with_gap(bus.slave_path(), "3.5chars"));
  ASSERT_TRUE(master.open());
  const std::vector<std::uint8_t> read_id{0x03, 0x00, 0x0A, 0x00, 0x01};
  for (int i = 0; i < 6; ++i) {
    const RtuExchange exchange = master.transact(1, read_id, 100ms);
    ASSERT_EQ(exchange.outcome, RtuOutcome::Reply) << "transaction " << i << ": " << exchange.detail;
  }
  EXPECT_EQ(bus.stats().merged_requests, 0u);
}

TEST(RtuMaster, WithoutAGapTheSlaveHearsTheNextRequestAsTheTailOfItsAnswer) {
  simulator::SimulatedBus bus(smsmb_servos({1}, kSlowRtuBaud));
  bus.start();
  RtuMaster master(line_with_gap(bus.slave_path(), "0us"));
  ASSERT_TRUE(master.open());
  const std::vector<std::uint8_t> read_id{0x03, 0x00, 0x0A, 0x00, 0x01};
  // The request leaves as soon as the answer is read: well within the servo's 7.3 ms. Up to a few
  // tries, in case a stalled machine delays one that long; one merge shows the rule bites.
  int timeouts = 0;
  for (int i = 0; i < 6 && bus.stats().merged_requests == 0; ++i) {
    if (master.transact(1, read_id, 30ms).outcome == RtuOutcome::Timeout) ++timeouts;
  }
  EXPECT_GT(bus.stats().merged_requests, 0u);
  EXPECT_GT(timeouts, 0) << "a merged request is not answered";
}

TEST(RtuMaster, OpenNamesAMissingDeviceAndWhatToDo) {
  RtuMaster master(RtuLineSettings{SerialSettings{"/dev/nonexistent-rtu-adapter", 115'200}, line_options()});
  const auto opened = master.open();
  ASSERT_FALSE(opened);
  EXPECT_NE(opened.error().find("/dev/nonexistent-rtu-adapter"), std::string::npos) << opened.error();
  EXPECT_NE(opened.error().find("plugged in"), std::string::npos) << opened.error();
}

class RtuEngineTest : public ::testing::Test {
 protected:
  void start(std::vector<std::uint8_t> ids, std::uint32_t baud = 115'200) {
    bus_ = std::make_unique<simulator::SimulatedBus>(smsmb_servos(ids, baud));
    bus_->start();
    engine_ = make_bus_engine(rtu_settings(bus_->slave_path(), ids, baud), line_options());
    engine_->start();
    ASSERT_TRUE(eventually([&] { return engine_->discovered(); })) << "discovery did not finish";
  }
  void TearDown() override {
    if (engine_) engine_->stop();
  }
  std::unique_ptr<simulator::SimulatedBus> bus_;
  std::unique_ptr<BusEngine> engine_;
};

TEST_F(RtuEngineTest, ReadsHoldingRegistersWithFc03) {
  start({1});
  const BusResult result = transact(*engine_, ReadOp{1, 0x0A, 2}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x00, 0x01, 0x00, 0x02}));  // ID 1, baud code 2 (115200)
}

TEST_F(RtuEngineTest, WritesOneRegisterWithFc06AndSeveralWithFc16) {
  start({1});
  // Torque limit 500: FC06.
  BusResult result = transact(*engine_, WriteOp{1, 0x84, Bytes{0x01, 0xF4}});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(bus_->read_field(1, "torque_limit"), 500);
  // Acceleration 10, running speed -100 (two's complement), torque limit 800: FC16.
  result = transact(*engine_, WriteOp{1, 0x82, Bytes{0x00, 0x0A, 0xFF, 0x9C, 0x03, 0x20}});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(bus_->read_field(1, "acceleration"), 10);
  EXPECT_EQ(bus_->read_field(1, "running_speed"), -100);
  EXPECT_EQ(bus_->read_field(1, "torque_limit"), 800);
}

TEST_F(RtuEngineTest, SlaveExceptionIsARefusalWithItsCode) {
  start({1});
  // Register 0x300 is beyond the table: the servo answers 0x02 (illegal data address).
  const BusResult result = transact(*engine_, ReadOp{1, 0x300, 1}, Priority::ClientRead);
  EXPECT_EQ(result.status, BusStatus::ServoRefused);
  EXPECT_EQ(result.servo_error, 0x02);
  EXPECT_NE(result.detail.find("illegal data address"), std::string::npos) << result.detail;
}

TEST_F(RtuEngineTest, BroadcastWriteReachesEveryServoWithoutAnAnswer) {
  start({1, 2});
  const BusResult result = transact(*engine_, WriteOp{0, 0x80, Bytes{0x04, 0x00}});
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(bus_->read_field(1, "goal_position"), 1024);
  EXPECT_EQ(bus_->read_field(2, "goal_position"), 1024);
  const BusResult raw = transact(*engine_, RawPduOp{0, Bytes{0x06, 0x00, 0x80, 0x02, 0x00}});
  ASSERT_EQ(raw.status, BusStatus::Ok) << raw.detail;
  EXPECT_TRUE(raw.data.empty());
  EXPECT_EQ(bus_->read_field(2, "goal_position"), 512);
}

TEST_F(RtuEngineTest, RetriesACorruptAnswer) {
  start({1});
  const auto before = engine_->counters();
  bus_->corrupt_next_replies(1);
  const BusResult result = transact(*engine_, ReadOp{1, 0x0A, 1}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x00, 0x01}));
  const auto after = engine_->counters();
  EXPECT_GE(after.checksum_errors + after.stray_frames, before.checksum_errors + before.stray_frames + 1);
  EXPECT_GE(after.retries, before.retries + 1);
}

TEST_F(RtuEngineTest, RawPduComesBackAsItIsExceptionsIncluded) {
  start({1});
  BusResult result = transact(*engine_, RawPduOp{1, Bytes{0x03, 0x00, 0x0A, 0x00, 0x01}}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x03, 0x02, 0x00, 0x01}));
  // FC04 is not supported by SMSMB servos (docs/PROTOCOL.md §1.3): the exception PDU is the answer.
  result = transact(*engine_, RawPduOp{1, Bytes{0x04, 0x01, 0x00, 0x00, 0x01}}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x84, 0x01}));
}

TEST_F(RtuEngineTest, RefusesOperationsModbusCannotExpress) {
  start({1});
  const auto ignore = [](BusResult) {};
  EXPECT_THROW(engine_->submit(ActionOp{}, Priority::ClientWrite, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(SyncWriteOp{}, Priority::ClientWrite, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(WriteOp{1, 0x80, Bytes{0, 1}, true}, Priority::ClientWrite, ignore),
               std::invalid_argument);
  EXPECT_THROW(engine_->submit(ReadOp{1, 0x100, 126}, Priority::ClientRead, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(ReadOp{0, 0x100, 1}, Priority::ClientRead, ignore), std::invalid_argument);
  EXPECT_THROW(engine_->submit(WriteOp{1, 0x80, Bytes{0x01}}, Priority::ClientWrite, ignore), std::invalid_argument);
}

TEST_F(RtuEngineTest, DiscoveryReadsEachServosIdentity) {
  start({1, 2});
  const auto memory = bus_->read_memory(2, 0x00, 2);  // firmware version, servo version
  ASSERT_TRUE(memory);
  const auto state = engine_->cache().state(2);
  ASSERT_TRUE(state);
  EXPECT_TRUE(state->online);
  EXPECT_EQ(state->identity.firmware, static_cast<std::uint16_t>((*memory)[0] << 8 | (*memory)[1]));
  EXPECT_EQ(state->identity.model, static_cast<std::uint16_t>((*memory)[2] << 8 | (*memory)[3]));
}

TEST_F(RtuEngineTest, PollsTheFeedbackBlockIntoTheCacheWithOneFc03PerServo) {
  start({1, 2});
  // The motion model rewrites present values on every access, so the feedback is changed the
  // way the servo itself would show it: an over-temperature fault sets status bit 2 (0x100)
  // and lifts the temperature (0x105) past the 70 °C default limit.
  bus_->set_error_bits(2, 0x04);
  Bytes block(16);
  ASSERT_TRUE(
      eventually([&] { return engine_->cache().copy(2, 0x100, block) == CacheRead::Ok && (block[1] & 0x04) != 0; }));
  Bytes temperature(2);
  ASSERT_EQ(engine_->cache().copy(2, 0x105, temperature), CacheRead::Ok);
  EXPECT_GE((temperature[0] << 8) | temperature[1], 73);
  Bytes other(2);
  ASSERT_EQ(engine_->cache().copy(1, 0x100, other), CacheRead::Ok);
  EXPECT_EQ(other[1] & 0x04, 0) << "the fault belongs to servo 2 only";
  // A cycle is counted once its last servo's answer is stored: shortly after the block shows.
  EXPECT_TRUE(eventually([&] { return engine_->counters().poll_cycles > 0; }));
}

TEST_F(RtuEngineTest, SilentServoGoesOfflineAndComesBackByItself) {
  start({1, 2});
  bus_->set_offline(2, true);
  ASSERT_TRUE(eventually([&] { return !engine_->cache().state(2)->online; }));
  // A client read of the offline servo is answered at once: it never goes on the wire, so no
  // timeouts are paid on the bus (the simulator hears no FC03 of register 0x0A from it).
  conformance::FrameLog frames(*bus_);
  const BusResult result = transact(*engine_, ReadOp{2, 0x0A, 1}, Priority::ClientRead);
  EXPECT_EQ(result.status, BusStatus::Timeout);
  for (const auto& frame : frames.frames()) {
    EXPECT_FALSE(frame.id == 2 && frame.code == 0x03 && frame.params == (Bytes{0x00, 0x0A, 0x00, 0x01}))
        << "the client's read of the offline servo went on the wire";
  }
  // The other servo keeps answering.
  EXPECT_EQ(transact(*engine_, ReadOp{1, 0x0A, 1}, Priority::ClientRead).status, BusStatus::Ok);
  bus_->set_offline(2, false);
  EXPECT_TRUE(eventually([&] { return engine_->cache().state(2)->online; }));
  EXPECT_EQ(transact(*engine_, ReadOp{2, 0x0A, 1}, Priority::ClientRead).status, BusStatus::Ok);
}

TEST(RtuEngine, LostPortGoesDownAndComesBackWhenTheDeviceReturns) {
  const std::string link =
      (std::filesystem::temp_directory_path() / ("rtu-engine-test-" + std::to_string(::getpid()))).string();
  auto options = smsmb_servos({1});
  options.link = link;
  auto bus = std::make_unique<simulator::SimulatedBus>(options);
  bus->start();
  const auto engine_owner = make_bus_engine(rtu_settings(link, {1}), line_options());
  BusEngine& engine = *engine_owner;
  engine.start();
  ASSERT_TRUE(eventually([&] { return engine.discovered(); }));
  bus->stop();
  bus.reset();
  ASSERT_TRUE(eventually([&] { return !engine.bus_up(); })) << "the engine did not notice the lost port";
  // While down, submissions are refused at once with BusDown.
  EXPECT_EQ(transact(engine, ReadOp{1, 0x0A, 1}).status, BusStatus::BusDown);
  bus = std::make_unique<simulator::SimulatedBus>(options);
  bus->start();
  ASSERT_TRUE(eventually([&] { return engine.bus_up() && engine.discovered(); }));
  EXPECT_EQ(transact(engine, ReadOp{1, 0x0A, 1}).status, BusStatus::Ok);
  EXPECT_GE(engine.counters().bus_down_events, 1U);
  engine.stop();
}

TEST(RtuEngine, FactoryBuildsTheRtuEngineForModbusRtuBuses) {
  auto engine = make_bus_engine(rtu_settings("/dev/null", {1}));
  EXPECT_NE(dynamic_cast<EngineCore<RtuTransactor>*>(engine.get()), nullptr);
  // A packet table on a modbus-rtu bus cannot be run.
  auto wrong = rtu_settings("/dev/null", {});
  wrong.servos.push_back({1, TableId::Sts, modbus_map::ByteOrder::LowFirst, AddressBlock{56, 15}});
  EXPECT_THROW(make_bus_engine(wrong), std::invalid_argument);
}

}  // namespace
}  // namespace sms::gateway
