#pragma once
// The integrator tools' line to the servos (scan, set-id, set-baud, calibrate-middle, dump):
// one servo transaction at a time, synchronously, on the tool's own thread — no engine, no
// queue, no polling, but the engine's own transactors (gateway/bus/transactor.h), so tools and
// gateway frame, judge, retry and refuse alike. One interface for the three bus protocols:
//   feetech / d55d: PING, READ, WRITE packets (PacketTransactor);
//   modbus-rtu:     FC03 / FC06 / FC16 (RtuTransactor, libmodbus).
// Addresses and counts are bus addresses: bytes on packet buses, registers on modbus-rtu
// (data then holds registers high byte first).
//
// Timeouts are sized from the baud (docs/PROTOCOL.md §5): the request's and the reply's wire time, plus
// the servo's usual return delay, plus the adapter latency (`LinkSettings::latency`).
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "config/config.h"
#include "modbus_map/control_table.h"
#include "protocol/bus_protocol.h"
#include "protocol/expected.h"
#include "protocol/packet.h"

namespace sms::gateway {

using protocol::Bytes;

// What the tools need to know of a bus protocol, as data.
struct ToolProtocol {
  protocol::BusProtocol protocol;
  modbus_map::TableId default_table;  // for identity and dumps when no --table is given
  std::uint8_t first_id;              // unicast IDs
  std::uint8_t last_id;
  std::uint8_t broadcast_id;
  // The factory return delay (sts 250 x 2 us, d55d 16 x 500 us, SMSMB 500 us): how long a
  // servo usually waits before answering, for the scan's per-ID timeout.
  std::chrono::microseconds usual_return_delay;
  bool broadcast_ping_answered;  // PING to the broadcast ID is answered by every servo
  // The instruction that puts a servo's whole table back to factory values (d55d RESET); none
  // where the protocol has no such instruction (feetech's RECOVERY restores the servo's own
  // backup, not factory values).
  std::optional<std::uint8_t> factory_reset;
};
const ToolProtocol& tool_protocol(protocol::BusProtocol protocol);

struct LinkSettings {
  std::string device;
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  std::uint32_t baud = 1'000'000;
  config::Parity parity = config::Parity::None;
  std::uint8_t stop_bits = 1;
  config::ModbusRtuOptions rtu;  // modbus-rtu only: RS-485 mode, RTS, byte timeout
  // Added to every reply timeout: the USB adapter's latency (an FTDI adapter holds short
  // replies up to its latency timer: 16 ms unless set to 1 ms) and scheduling jitter.
  std::chrono::milliseconds latency{5};
  unsigned attempts = 3;  // per transaction, on timeouts and corrupt replies
};

enum class LinkStatus : std::uint8_t {
  Ok,
  Timeout,    // nothing valid from the addressed ID in time
  Corrupt,    // only damaged frames (checksum / CRC), or frames from another ID
  Refused,    // the servo refused: packet ERROR refusal bits without data, or a Modbus exception
  PortError,  // the device failed
};
std::string_view to_string(LinkStatus status);

struct LinkAnswer {
  LinkStatus status = LinkStatus::Timeout;
  Bytes data;  // READ: the bytes (packet) or registers high byte first (modbus)
  std::uint8_t servo_status =
      0;  // packet: the ERROR byte; modbus: the exception code (Refused, or a PING answered with one)
  bool heard_anything = false;          // some bytes came back, valid or not (collisions, other IDs)
  std::vector<std::uint8_t> other_ids;  // valid answers from other IDs heard meanwhile (late answers)
  bool damaged = false;                 // bytes that made no valid frame came back (colliding answers, noise)
  // Bytes that waited unread on the line and were dropped before the request went out: the late
  // answer of the transaction before (its servo answered after that one gave up), or noise.
  std::size_t dropped_before = 0;
  std::string detail;

  bool ok() const { return status == LinkStatus::Ok; }
};

class ServoLink {
 public:
  virtual ~ServoLink() = default;

  // Opens the device at settings().baud. The error says what to do.
  virtual Expected<Ok> open() = 0;
  // Changes the line rate (reopening where the transport needs it).
  virtual Expected<Ok> set_baud(std::uint32_t baud) = 0;
  virtual const LinkSettings& settings() const = 0;
  virtual void set_attempts(unsigned attempts) = 0;
  virtual void set_latency(std::chrono::milliseconds latency) = 0;

  // Is anything there? feetech/d55d: PING; modbus-rtu: FC03 of register 0 (an exception
  // answer counts as present: servo_status holds its code). A PING to the broadcast ID is Ok
  // as soon as any servo's answer arrives (they collide; heard_anything says something came).
  virtual LinkAnswer ping(std::uint8_t id) = 0;
  virtual LinkAnswer read(std::uint8_t id, std::uint16_t address, std::uint16_t count) = 0;
  // To the broadcast ID: sent, nothing awaited (Ok once it left the wire).
  virtual LinkAnswer write(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> data) = 0;
  // An instruction without parameters (packet protocols; ToolProtocol::factory_reset), awaiting
  // its status packet. modbus-rtu has none: PortError saying so.
  virtual LinkAnswer instruction(std::uint8_t id, std::uint8_t code) = 0;

  // Wire time of `bytes` characters at the current rate.
  virtual std::chrono::nanoseconds wire_time(std::size_t bytes) const = 0;
};

std::unique_ptr<ServoLink> make_servo_link(const LinkSettings& settings);

// The reply timeout of a transaction: request and reply wire time, the protocol's usual return
// delay and the link's latency.
std::chrono::nanoseconds tool_reply_timeout(const ServoLink& link, std::size_t request_bytes, std::size_t reply_bytes);

}  // namespace sms::gateway
