// SMS servos with Modbus-RTU firmware (SMSMB, docs/PROTOCOL.md §1.3 and §2.4) through a real pty: the
// frames by hand, then a stock libmodbus RTU master as proof the slave side is standard.
#include <gtest/gtest.h>
#include <modbus.h>

#include <cerrno>
#include <thread>

#include "tests/simulator/sim_fixture.h"

namespace sms::simulator::testing {
namespace {

class SmsmbSim : public ::testing::Test {
 protected:
  void start(std::vector<ServoConfig> servos) { rig = std::make_unique<Rig>(quick_options(std::move(servos))); }
  HostPort& host() { return *rig->host; }

  // Sends a whole ADU (CRC included) and returns whatever comes back.
  // Whatever comes within `limit` (300 ms: where silence is the answer), until the line is quiet.
  Bytes exchange(const Bytes& adu, std::chrono::milliseconds limit = std::chrono::milliseconds(300)) {
    host().send(adu);
    return host().receive(std::chrono::milliseconds(20), limit);
  }
  // For a request that is answered: awaited as long as a loaded machine holds the simulator back
  // (300 ms was not enough beside the test command's lanes).
  Bytes answered(const Bytes& adu) { return exchange(adu, std::chrono::milliseconds(5000)); }
  // One holding register through FC 03, framed by the foundation codec.
  std::optional<std::uint16_t> reg(std::uint8_t slave, std::uint16_t address) {
    const Bytes pdu{0x03, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address), 0x00, 0x01};
    const Bytes reply = answered(protocol::rtu::frame(slave, pdu));
    if (reply.size() != 7 || reply[1] != 0x03) return std::nullopt;
    return static_cast<std::uint16_t>(reply[3] << 8 | reply[4]);
  }
  void set(std::uint8_t slave, std::uint16_t address, std::uint16_t value) {
    const Bytes pdu{0x06, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
                    static_cast<std::uint8_t>(value >> 8), static_cast<std::uint8_t>(value)};
    const Bytes request = protocol::rtu::frame(slave, pdu);
    ASSERT_EQ(answered(request), request) << "FC 06 echo for register " << address;
  }
  bool reaches(std::uint8_t slave, std::uint16_t address, std::uint16_t value) {
    return eventually([&] { return reg(slave, address) == value; });
  }

  std::unique_ptr<Rig> rig;
};

TEST_F(SmsmbSim, WorkedFrameReadsTheEightFeedbackRegisters) {
  start({smsmb(1)});
  // status 0 (torque off), position 2048, speed 0, PWM 0, 12.1 V, 28 °C, not moving, 0 mA
  EXPECT_EQ(exchange({0x01, 0x03, 0x01, 0x00, 0x00, 0x08, 0x45, 0xF0}),
            (Bytes{0x01, 0x03, 0x10, 0x00, 0x00, 0x08, 0x00, 0x00, 0x00, 0x00, 0x00,
                   0x00, 0x79, 0x00, 0x1C, 0x00, 0x00, 0x00, 0x00, 0xD4, 0x94}));
}

TEST_F(SmsmbSim, WorkedFrameSetsTheGoalAndIsEchoed) {
  start({smsmb(1)});
  set(1, 0x80, 3000);
  const Bytes request{0x01, 0x06, 0x00, 0x80, 0x08, 0x00, 0x8F, 0xE2};
  EXPECT_EQ(exchange(request), request);
  EXPECT_EQ(reg(1, 0x81), 1) << "a goal switches the torque on";
}

TEST_F(SmsmbSim, WriteMultipleSetsGoalAndTorqueAndTheServoMoves) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x10, 0x00, 0x80, 0x00, 0x02, 0x04, 0x0C, 0x00, 0x00, 0x01, 0x39, 0x5F}),
            (Bytes{0x01, 0x10, 0x00, 0x80, 0x00, 0x02, 0x40, 0x20}));
  EXPECT_EQ(exchange({0x01, 0x03, 0x00, 0x80, 0x00, 0x02, 0xC5, 0xE3}),
            (Bytes{0x01, 0x03, 0x04, 0x0C, 0x00, 0x00, 0x01, 0x38, 0xA3}));
  EXPECT_TRUE(reaches(1, 0x101, 0x0C00));
  EXPECT_EQ(reg(1, 0x106), 0) << "moving flag cleared on arrival";
  EXPECT_EQ(reg(1, 0x100), 0x10) << "status bit 4: torque on";
}

TEST_F(SmsmbSim, InputRegistersAreRefusedWithIllegalFunctionAsTheRealServoDoes) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x04, 0x01, 0x00, 0x00, 0x08, 0xF0, 0x30}), (Bytes{0x01, 0x84, 0x01, 0x82, 0xC0}));
}

TEST_F(SmsmbSim, UnknownFunctionIsRefusedWithIllegalFunction) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x2B, 0x0E, 0xBF, 0x34}), (Bytes{0x01, 0xAB, 0x01, 0x9E, 0xF0}));
}

TEST_F(SmsmbSim, ReadBeyondTheMapIsIllegalAddress) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x03, 0x02, 0x00, 0x00, 0x01, 0x85, 0xB2}), (Bytes{0x01, 0x83, 0x02, 0xC0, 0xF1}));
}

TEST_F(SmsmbSim, ReadOfAnUndefinedRegisterIsIllegalAddress) {
  start({smsmb(1)});
  // Registers 0x04-0x09 are no field (wiki memory-smsmb): not a made-up 0 but exception 0x02,
  // alone or inside a range that starts on a defined register.
  for (const std::uint16_t first : {std::uint16_t{0x04}, std::uint16_t{0x00}}) {
    const std::uint16_t count = first == 0x04 ? 1 : 0x0C;
    const Bytes pdu{0x03, 0x00, static_cast<std::uint8_t>(first), 0x00, static_cast<std::uint8_t>(count)};
    const Bytes reply = exchange(protocol::rtu::frame(1, pdu));
    ASSERT_GE(reply.size(), 3U) << "register " << first;
    EXPECT_EQ(reply[1], 0x83) << "register " << first;
    EXPECT_EQ(reply[2], 0x02) << "register " << first;
  }
}

TEST_F(SmsmbSim, ReadOfZeroRegistersIsIllegalValue) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x03, 0x00, 0x0A, 0x00, 0x00, 0x65, 0xC8}), (Bytes{0x01, 0x83, 0x03, 0x01, 0x31}));
}

TEST_F(SmsmbSim, WriteToReadOnlyRegisterIsIllegalAddressAndNothingWritten) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x06, 0x01, 0x01, 0x00, 0x00, 0xD9, 0xF6}), (Bytes{0x01, 0x86, 0x02, 0xC3, 0xA1}));
  EXPECT_EQ(reg(1, 0x101), 2048);
}

TEST_F(SmsmbSim, ValueOutsideTheRegisterRangeIsIllegalValue) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x06, 0x00, 0x81, 0x00, 0x05, 0x19, 0xE1}), (Bytes{0x01, 0x86, 0x03, 0x02, 0x61}));
  EXPECT_EQ(reg(1, 0x81), 0);
}

TEST_F(SmsmbSim, ReportSlaveIdCarriesTheStatus) {
  start({smsmb(1)});
  EXPECT_EQ(exchange({0x01, 0x11, 0xC0, 0x2C}), (Bytes{0x01, 0x11, 0x03, 0x01, 0x00, 0x00, 0xAC, 0x4D}));
  rig->bus->set_error_bits(1, 0x04);  // temperature
  EXPECT_EQ(exchange({0x01, 0x11, 0xC0, 0x2C}), (Bytes{0x01, 0x11, 0x03, 0x01, 0x00, 0x04, 0xAD, 0x8E}));
}

TEST_F(SmsmbSim, RestartIsAcknowledgedThenDeafThenBackWithRamDefaults) {
  start({smsmb(1)});
  set(1, 0x82, 9);
  EXPECT_EQ(exchange({0x01, 0x41, 0xC0, 0x10}), (Bytes{0x01, 0x41, 0xC0, 0x10}));
  EXPECT_TRUE(exchange({0x01, 0x11, 0xC0, 0x2C}).empty()) << "deaf while restarting";
  std::this_thread::sleep_for(std::chrono::milliseconds(120));
  EXPECT_EQ(reg(1, 0x82), 0);
}

TEST_F(SmsmbSim, BroadcastWriteExecutesOnEverySlaveSilently) {
  start({smsmb(1), smsmb(2)});
  EXPECT_TRUE(exchange({0x00, 0x06, 0x00, 0x82, 0x00, 0x09, 0xE8, 0x35}).empty());
  EXPECT_EQ(exchange({0x01, 0x03, 0x00, 0x82, 0x00, 0x01, 0x24, 0x22}),
            (Bytes{0x01, 0x03, 0x02, 0x00, 0x09, 0x78, 0x42}));
  EXPECT_EQ(exchange({0x02, 0x03, 0x00, 0x82, 0x00, 0x01, 0x24, 0x11}),
            (Bytes{0x02, 0x03, 0x02, 0x00, 0x09, 0x3C, 0x42}));
}

TEST_F(SmsmbSim, CorruptRequestIsIgnored) {
  start({smsmb(1)});
  EXPECT_TRUE(exchange({0x01, 0x03, 0x01, 0x00, 0x00, 0x08, 0x45, 0xF1}).empty());
  EXPECT_EQ(rig->bus->stats().checksum_errors, 1U);
}

TEST_F(SmsmbSim, NegativeGoalIsTwosComplementInStepperMode) {
  start({smsmb(1)});
  set(1, 0x10, 4);       // stepper: relative moves
  set(1, 0x80, 0xFF9C);  // -100
  EXPECT_TRUE(reaches(1, 0x101, 1948));
  EXPECT_EQ(exchange({0x01, 0x03, 0x01, 0x01, 0x00, 0x01, 0xD4, 0x36}),
            (Bytes{0x01, 0x03, 0x02, 0x07, 0x9C, 0xBA, 0x1D}));
}

TEST_F(SmsmbSim, ModeThreeLetsGoOfTheTorqueOnArrival) {
  start({smsmb(1)});
  set(1, 0x10, 3);
  set(1, 0x80, 2200);
  EXPECT_TRUE(reaches(1, 0x101, 2200));
  EXPECT_TRUE(reaches(1, 0x81, 0));
}

TEST_F(SmsmbSim, FaultResetBitTwoSetsTheCentre) {
  start({smsmb(1)});
  set(1, 0x80, 3000);
  ASSERT_TRUE(reaches(1, 0x101, 3000));
  set(1, 0x86, 0x04);
  EXPECT_EQ(reg(1, 0x101), 2048);
  EXPECT_EQ(exchange({0x01, 0x03, 0x00, 0x0F, 0x00, 0x01, 0xB4, 0x09}),
            (Bytes{0x01, 0x03, 0x02, 0x03, 0xB8, 0xB8, 0xC6}))
      << "calibration register 952 = 3000 - 2048";
  EXPECT_EQ(reg(1, 0x86), 0) << "fault reset reads back 0";
}

TEST_F(SmsmbSim, FaultResetClearsTheLatchedFault) {
  start({smsmb(1)});
  rig->bus->set_error_bits(1, 0x04);  // temperature
  EXPECT_EQ(reg(1, 0x100), 0x04);
  set(1, 0x86, 0x40);  // bit 6 overheat
  EXPECT_EQ(reg(1, 0x100), 0x00);
}

TEST_F(SmsmbSim, UnlockedEepromSurvivesRestartLockedDoesNot) {
  start({smsmb(1)});
  set(1, 0x0D, 100);  // min angle limit, lock 1 (default)
  EXPECT_EQ(exchange({0x01, 0x41, 0xC0, 0x10}), (Bytes{0x01, 0x41, 0xC0, 0x10}));
  std::this_thread::sleep_for(std::chrono::milliseconds(120));
  EXPECT_EQ(reg(1, 0x0D), 0);
  set(1, 0x85, 0);
  set(1, 0x0D, 100);
  EXPECT_EQ(exchange({0x01, 0x41, 0xC0, 0x10}), (Bytes{0x01, 0x41, 0xC0, 0x10}));
  std::this_thread::sleep_for(std::chrono::milliseconds(120));
  EXPECT_EQ(reg(1, 0x0D), 100);
}

TEST_F(SmsmbSim, ChangedSlaveIdAnswersUnderTheNewId) {
  start({smsmb(1)});
  set(1, 0x0A, 5);
  EXPECT_TRUE(exchange({0x01, 0x11, 0xC0, 0x2C}).empty());
  EXPECT_EQ(reg(5, 0x0A), 5);
}

// --- a stock Modbus master ------------------------------------------------------------------

struct ModbusDeleter {
  void operator()(modbus_t* context) const {
    modbus_close(context);
    modbus_free(context);
  }
};

TEST_F(SmsmbSim, StockLibmodbusRtuMasterTalksToIt) {
  start({smsmb(1), smsmb(2)});
  const std::unique_ptr<modbus_t, ModbusDeleter> master(
      modbus_new_rtu(rig->bus->slave_path().c_str(), 115200, 'N', 8, 1));
  ASSERT_NE(master, nullptr);
  ASSERT_EQ(modbus_connect(master.get()), 0) << modbus_strerror(errno);
  modbus_set_response_timeout(master.get(), 0, 300'000);

  ASSERT_EQ(modbus_set_slave(master.get(), 2), 0);
  std::uint16_t feedback[8] = {};
  ASSERT_EQ(modbus_read_registers(master.get(), 0x100, 8, feedback), 8) << modbus_strerror(errno);
  EXPECT_EQ(feedback[1], 2048);
  EXPECT_EQ(feedback[4], 121);

  ASSERT_EQ(modbus_write_register(master.get(), 0x80, 2100), 1) << modbus_strerror(errno);
  const std::uint16_t limits[2] = {10, 4000};
  ASSERT_EQ(modbus_write_registers(master.get(), 0x0D, 2, limits), 2) << modbus_strerror(errno);
  std::uint16_t back[2] = {};
  ASSERT_EQ(modbus_read_registers(master.get(), 0x0D, 2, back), 2);
  EXPECT_EQ(back[0], 10);
  EXPECT_EQ(back[1], 4000);

  std::uint16_t input[1] = {};
  EXPECT_EQ(modbus_read_input_registers(master.get(), 0x100, 1, input), -1);
  EXPECT_EQ(errno, EMBXILFUN);
  EXPECT_EQ(modbus_read_registers(master.get(), 0x300, 1, input), -1);
  EXPECT_EQ(errno, EMBXILADD);
}

// A slave's own t3.5, with wire timing on: a request that starts less than 3.5
// characters after the previous frame is heard as its tail and ignored; after a silence the
// slave listens again.
TEST_F(SmsmbSim, RequestCloserThanThreePointFiveCharactersToThePreviousFrameIsIgnored) {
  BusOptions options = quick_options({smsmb(1)});
  options.timing = true;
  rig = std::make_unique<Rig>(options);
  const Bytes read = protocol::rtu::frame(1, Bytes{0x03, 0x00, 0x80, 0x00, 0x01});
  Bytes both = read;
  both.insert(both.end(), read.begin(), read.end());          // back to back: no silence between them
  std::this_thread::sleep_for(std::chrono::milliseconds(5));  // the line was just opened
  host().send(both);
  const Bytes answers = host().receive_answer(7);
  EXPECT_EQ(answers.size(), 7u) << "only the first request is answered";
  EXPECT_EQ(rig->bus->stats().merged_requests, 1u);

  // A silence longer than t3.5 first (3.5 characters at 115200 bit/s are 304 us): answered.
  std::this_thread::sleep_for(std::chrono::milliseconds(5));
  host().send(read);
  EXPECT_EQ(host().receive_exactly(7).size(), 7u);
  EXPECT_EQ(rig->bus->stats().merged_requests, 1u);
}

}  // namespace
}  // namespace sms::simulator::testing
