#pragma once
// A whole simulated servo bus in-process: a pseudo-terminal (or a real serial device), a
// thread answering on it, and N virtual servos, each with its own ID, table, protocol and
// baud (docs/PROTOCOL.md §1-§3). The host opens slave_path() like any serial port.
//
//   sms::simulator::SimulatedBus bus(sms::simulator::default_bus_options());
//   bus.start();
//   open(bus.slave_path().c_str(), ...);   // 6 sts servos, IDs 1-6, feetech, 1 Mbaud
//
// Every control method is thread-safe and may be called while the bus runs (tests inject
// faults between transactions). A servo is addressed by its current ID; when several servos
// share an ID (add_duplicate, or a mixed bus), the call applies to each of them.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"
#include "protocol/bus_protocol.h"
#include "protocol/packet.h"

namespace sms::simulator {

struct ServoConfig {
  std::uint8_t id = 1;
  modbus_map::TableId table = modbus_map::TableId::Sts;
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  std::uint32_t baud = 1'000'000;
  friend bool operator==(const ServoConfig&, const ServoConfig&) = default;
};

struct BusOptions {
  std::vector<ServoConfig> servos;
  // Replies wait for the wire time (request + return delay + reply at 10 bits a character).
  bool timing = true;
  // Attach to this serial device instead of creating a pty (the device is set to the first
  // servo's baud; servos at other rates then never answer, as on a real bus).
  std::string device;
  // Create this symlink to the pty slave (replaced if it is a symlink already; removed at stop).
  std::string link;
  // EEPROM persistence across restarts (unlocked EEPROM writes survive). Empty: none.
  std::string state_file;
  // How long a servo stays deaf after REBOOT / Modbus restart (0x41).
  std::chrono::milliseconds reboot_time{500};
  // Seed for the fault-injection dice; 0 picks a random seed.
  std::uint32_t seed = 0;
};

// The gateway's `--simulate` bus: 6 sts servos, IDs 1-6, feetech, 1 000 000 baud.
BusOptions default_bus_options();

// What one servo looks like right now, for listings and assertions.
struct ServoSummary {
  ServoConfig config;  // current ID and baud (they follow writes to the table)
  bool duplicate = false;
  bool offline = false;
  std::int32_t present_position = 0;  // as a Modbus client sees it (signed)
  std::int32_t goal_position = 0;
  bool moving = false;
  // When a goal was last written in position mode and when the motor then reached it.
  std::optional<std::chrono::steady_clock::time_point> move_started;
  std::optional<std::chrono::steady_clock::time_point> arrived;
  double position_at_goal = 0;        // where the motor was when that goal was written
  double read_before_goal = 0;        // where it was when it answered the last read before that write
  bool reversed = false;              // it turned back since its last command
  double turned_back = 0;             // how far, from the farthest point it reached
  std::uint64_t heartbeat_stops = 0;  // d55d: times its heartbeat stopped it (500 ms without an instruction)
};

struct BusStats {
  std::uint64_t requests = 0;         // frames decoded (any servo, any protocol)
  std::uint64_t replies = 0;          // replies written to the line
  std::uint64_t dropped = 0;          // replies dropped by fault injection
  std::uint64_t corrupted = 0;        // replies corrupted by fault injection
  std::uint64_t collisions = 0;       // replies that overlapped another on the wire
  std::uint64_t checksum_errors = 0;  // request frames with a bad checksum or CRC
  // Modbus-RTU requests that began less than 3.5 characters after the previous frame (wire
  // timing on): a slave hears them as the tail of that frame and ignores them.
  std::uint64_t merged_requests = 0;
};

// A time the machine held the bus thread: it woke `held` after the moment it had asked to (its
// wake-up comes every few milliseconds whether or not a frame comes). Meanwhile no request was
// read and no reply sent: the witness tests ask before they call a servo's silence the gateway's
// doing (tests/README.md "Counting on a loaded machine").
struct Hold {
  std::chrono::steady_clock::time_point ended;
  std::chrono::steady_clock::duration held{};
};

// One request frame the bus decoded (any servo, any protocol), for programs that time what a
// host sends (bench/trip_latency). With wire timing on, `wire_end` is when the last byte of the
// read that completed the frame ends on the modelled wire (several frames read at once share
// it); without timing it is `arrived` plus the bytes' wire time all the same.
struct ReceivedFrame {
  std::chrono::steady_clock::time_point arrived;  // its last bytes were read from the line
  std::chrono::steady_clock::time_point wire_end;
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  std::uint8_t id = 0;     // packet ID (0xFE broadcast) or Modbus slave address
  std::uint8_t code = 0;   // instruction, or Modbus function code
  protocol::Bytes params;  // packet parameters, or the Modbus PDU after the function code
};
// Runs on the bus thread with the bus locked, before the servos handle the frame: keep it short
// and do not call the SimulatedBus from it.
using FrameObserver = std::function<void(const ReceivedFrame&)>;

class SimulatedBus {
 public:
  // Throws std::invalid_argument when a servo's table does not speak its protocol or its
  // baud is not in the protocol's baud table (docs/PROTOCOL.md §3), with the valid choices.
  explicit SimulatedBus(BusOptions options);
  ~SimulatedBus();  // stops
  SimulatedBus(const SimulatedBus&) = delete;
  SimulatedBus& operator=(const SimulatedBus&) = delete;

  // Opens the pty (or device), loads the state file, starts the thread. Throws
  // std::runtime_error / std::system_error with what failed and where.
  void start();
  void stop();
  bool running() const;
  // The path a host opens (/dev/pts/N, or the device). Empty before start().
  std::string slave_path() const;

  // --- fault injection -------------------------------------------------------------------
  void set_offline(std::uint8_t id, bool offline);
  void set_drop_probability(double probability);     // each reply dropped with probability p
  void set_corrupt_probability(double probability);  // each reply gets one byte flipped
  void corrupt_next_replies(unsigned count = 1);
  void drop_next_replies(unsigned count = 1);  // the next `count` replies are never sent
  // Every reply of this servo gets one byte flipped (the other servos stay clean) until
  // cleared: a servo answering garbage.
  void set_garbled(std::uint8_t id, bool garbled);
  // Extra delay on top of the wire time: the reply arrives after the host gave up.
  void set_reply_delay(std::uint8_t id, std::chrono::milliseconds extra);
  // The servo reports these ERROR / status bits (protocol's own bit meanings, docs/PROTOCOL.md §1) and
  // behaves accordingly (temperature/voltage readings, unload conditions). 0 clears.
  void set_error_bits(std::uint8_t id, std::uint8_t bits);
  // A second servo with the same ID, table, protocol and baud (its position differs a little):
  // both answer at once and their replies collide on the wire.
  void add_duplicate(std::uint8_t id);
  void set_timing(bool enabled);

  // --- memory access for assertions (no bus traffic, no wire time) ----------------------
  // Byte tables: `count` bytes from byte address `address`. SMSMB: `count` registers, two
  // bytes each, high byte first (as on the wire). The motion model is advanced first.
  // nullopt when no servo has the ID or the range leaves the table.
  std::optional<protocol::Bytes> read_memory(std::uint8_t id, std::uint16_t address, std::uint16_t count);
  // Raw write into the table with the same effects as a bus WRITE (read-only fields included:
  // this is the test's backdoor). Returns false when no servo has the ID or the range leaves
  // the table.
  bool write_memory(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> bytes);
  // A field by its modbus_map name, decoded (signed where the field is). nullopt: no such
  // servo or field.
  std::optional<std::int32_t> read_field(std::uint8_t id, std::string_view field_name);

  std::vector<ServoSummary> servos() const;
  BusStats stats() const;
  // The last holds of 5 ms or more (at most 256), oldest first.
  std::vector<Hold> holds() const;
  // Called for every request frame decoded from now on (checksum errors excluded); an empty
  // function removes it.
  void set_frame_observer(FrameObserver observer);

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::simulator
