#pragma once
// What the engine conformance suite (tests/gateway/bus/conformance_test.cpp) needs to run one set of
// cases against every bus protocol: per protocol the table its servos speak, the rate, a
// feedback block to read live, a RAM field the cases write, a field whose value is known
// (the servo's ID) and the status bits a servo can report; plus a recorder of the frames the
// simulator hears and a client that keeps writes queued on an engine.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <ostream>
#include <string>
#include <thread>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "protocol/instructions.h"
#include "simulator/simulated_bus.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway::conformance {

using namespace std::chrono_literals;

// One bus protocol as the suite drives it. Addresses are bus addresses: bytes on packet buses,
// registers on modbus-rtu buses.
struct ProtocolCase {
  std::string name;
  protocol::BusProtocol protocol;
  modbus_map::TableId table;
  std::uint32_t baud;
  AddressBlock feedback;       // readable live, and what the poll caches
  std::uint16_t ram_field;     // writable, one byte / one register, in RAM (no EEPROM wear)
  std::uint8_t legal_value;    // a value it takes; 1..200 are all legal for every case
  std::uint16_t id_field;      // reads back the servo's own ID
  std::uint8_t refusal_bit;    // an ERROR bit that makes the servo's answer to a WRITE a refusal; 0: none
  std::uint8_t condition_bit;  // an ERROR / status bit for a condition (recorded, logged)

  bool registers() const { return protocol == protocol::BusProtocol::ModbusRtu; }
  // One value of the RAM field (or the ID field) as the bus carries it.
  protocol::Bytes value(std::uint8_t v) const { return registers() ? protocol::Bytes{0, v} : protocol::Bytes{v}; }
  WriteOp write(std::uint8_t servo_id, std::uint8_t v) const { return WriteOp{servo_id, ram_field, value(v)}; }
  ReadOp read_feedback(std::uint8_t servo_id) const { return ReadOp{servo_id, feedback.address, feedback.count}; }
  ReadOp read_id(std::uint8_t servo_id) const { return ReadOp{servo_id, id_field, 1}; }

  // The value a request frame writes into the RAM field of `servo_id`, if it is such a write
  // (packet WRITE at the field; Modbus FC06 at the register).
  std::optional<std::uint8_t> written_value(const simulator::ReceivedFrame& frame, std::uint8_t servo_id) const {
    if (frame.id != servo_id) return std::nullopt;
    const auto& p = frame.params;
    if (registers()) {
      constexpr std::uint8_t kWriteSingleRegister = 0x06;
      if (frame.code != kWriteSingleRegister || p.size() != 4) return std::nullopt;
      if ((p[0] << 8 | p[1]) != ram_field || p[2] != 0) return std::nullopt;
      return p[3];
    }
    if (frame.code != protocol::common::kWrite || p.size() != 2 || p[0] != ram_field) return std::nullopt;
    return p[1];
  }
};
inline void PrintTo(const ProtocolCase& c, std::ostream* out) { *out << c.name; }

// The three buses the gateway drives: feetech with sts servos, d55d, modbus-rtu with SMSMB
// servos. Condition bit 0 is feetech's voltage, d55d's over-temperature and SMSMB's voltage
// bit; refusal bits: feetech 4, d55d 5 (instruction error), SMSMB none (exceptions instead).
inline std::vector<ProtocolCase> protocol_cases() {
  using modbus_map::TableId;
  using protocol::BusProtocol;
  return {
      {"feetech_sts", BusProtocol::Feetech, TableId::Sts, 1'000'000, {56, 15}, 41, 100, 5, 0x10, 0x01},
      {"d55d", BusProtocol::D55d, TableId::D55d, 115'200, {36, 8}, 34, 100, 3, 0x20, 0x01},
      {"modbus_rtu_smsmb", BusProtocol::ModbusRtu, TableId::Smsmb, 115'200, {0x100, 8}, 0x82, 100, 0x0A, 0, 0x01},
  };
}

// The simulator's servos `ids` and an engine's settings for them, as the other engine tests
// make them (bus_test_support.h: 50 ms response timeout, 10 ms poll, 200 ms probe period).
inline simulator::BusOptions servos(const ProtocolCase& c, std::vector<std::uint8_t> ids) {
  return testing::simulated_servos(std::move(ids), c.table, c.baud);
}
inline BusSettings settings(const ProtocolCase& c, std::string device, std::vector<std::uint8_t> ids) {
  BusSettings s = testing::bus_settings(std::move(device), std::move(ids), c.table, c.baud);
  EXPECT_EQ(s.protocol, c.protocol);
  for (auto& servo : s.servos) servo.poll_block = c.feedback;
  return s;
}

// Every request frame the simulator decodes, from construction on (the bus must outlive it).
class FrameLog {
 public:
  explicit FrameLog(simulator::SimulatedBus& bus) : bus_(bus) {
    bus_.set_frame_observer([this](const simulator::ReceivedFrame& frame) {
      std::lock_guard lock(mutex_);
      frames_.push_back(frame);
    });
  }
  ~FrameLog() { bus_.set_frame_observer({}); }
  FrameLog(const FrameLog&) = delete;
  FrameLog& operator=(const FrameLog&) = delete;

  std::vector<simulator::ReceivedFrame> frames() const {
    std::lock_guard lock(mutex_);
    return frames_;
  }
  void clear() {
    std::lock_guard lock(mutex_);
    frames_.clear();
  }
  // The values written into the case's RAM field of `servo_id`, in the order they arrived.
  std::vector<std::uint8_t> writes(const ProtocolCase& c, std::uint8_t servo_id) const {
    std::vector<std::uint8_t> values;
    for (const auto& frame : frames()) {
      if (const auto v = c.written_value(frame, servo_id)) values.push_back(*v);
    }
    return values;
  }
  // When each frame addressed to `servo_id` (unicast) arrived.
  std::vector<std::chrono::steady_clock::time_point> addressed_to(std::uint8_t servo_id) const {
    std::vector<std::chrono::steady_clock::time_point> times;
    for (const auto& frame : frames()) {
      if (frame.id == servo_id) times.push_back(frame.arrived);
    }
    return times;
  }

 private:
  simulator::SimulatedBus& bus_;
  mutable std::mutex mutex_;
  std::vector<simulator::ReceivedFrame> frames_;
};

// A run of frames writing the same value: one write and its retries, when the writer never writes
// one value twice in a row.
struct HeardWrite {
  std::uint8_t value = 0;
  unsigned attempts = 0;
};
inline std::vector<HeardWrite> attempts_per_value(const std::vector<std::uint8_t>& values) {
  std::vector<HeardWrite> heard;
  for (const auto value : values) {
    if (heard.empty() || heard.back().value != value) heard.push_back({value, 0});
    ++heard.back().attempts;
  }
  return heard;
}
// The writes `heard` carried, each with its retries once, and the most attempts any of them took.
inline std::vector<std::uint8_t> values_of(const std::vector<HeardWrite>& heard) {
  std::vector<std::uint8_t> values;
  for (const auto& write : heard) values.push_back(write.value);
  return values;
}
inline unsigned most_attempts(const std::vector<HeardWrite>& heard) {
  unsigned most = 0;
  for (const auto& write : heard) most = std::max(most, write.attempts);
  return most;
}

// One client writing the case's RAM field of servos 1-3 as fast as the engine takes it, with
// `depth` writes in flight at all times, until stop(): a flood of client work. Values 1-200.
class WriteFlood {
 public:
  WriteFlood(BusEngine& engine, const ProtocolCase& c, unsigned depth)
      : thread_([state = state_, &engine, c, depth] {
          unsigned sent = 0;
          while (state->running) {
            while (state->running && state->in_flight < depth) {
              ++state->in_flight;
              ++sent;
              const auto id = static_cast<std::uint8_t>(1 + sent % 3);
              engine.submit(c.write(id, static_cast<std::uint8_t>(1 + sent % 200)), Priority::ClientWrite,
                            [state](BusResult result) {
                              ++(result.status == BusStatus::Ok        ? state->answered
                                 : result.status == BusStatus::Timeout ? state->timed_out
                                                                       : state->failed);
                              --state->in_flight;
                            });
            }
            std::this_thread::sleep_for(100us);
          }
        }) {}
  ~WriteFlood() { stop(); }
  WriteFlood(const WriteFlood&) = delete;
  WriteFlood& operator=(const WriteFlood&) = delete;

  // Stops submitting and waits (at most 5 s) for the writes in flight to be answered.
  void stop() {
    state_->running = false;
    if (thread_.joinable()) thread_.join();
    EXPECT_TRUE(testing::eventually([&] { return state_->in_flight == 0; })) << "writes of the flood unanswered";
  }
  unsigned answered() const { return state_->answered.load(); }  // with Ok
  // answered(), callable from a completion even after the flood is gone.
  std::function<unsigned()> answered_counter() const {
    return [state = state_] { return state->answered.load(); };
  }
  // Answered Timeout: the servo did not answer within 1 + retries response timeouts, or was
  // offline after that until its probe (the engine's rule; on a loaded machine the simulator can
  // be descheduled for longer than that).
  unsigned timed_out() const { return state_->timed_out.load(); }
  unsigned failed() const { return state_->failed.load(); }  // any other answer

 private:
  struct State {  // shared with the completions, which may outlive a failed test's flood
    std::atomic<bool> running{true};
    std::atomic<unsigned> in_flight{0};
    std::atomic<unsigned> answered{0};
    std::atomic<unsigned> timed_out{0};
    std::atomic<unsigned> failed{0};
  };
  std::shared_ptr<State> state_ = std::make_shared<State>();
  std::thread thread_;  // last: starts once state_ exists
};

}  // namespace sms::gateway::conformance
