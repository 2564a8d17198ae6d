#pragma once
// Bus frames described for people (the bus monitor, docs/MONITOR.md), sans-IO: feed the bytes
// that went to the servos and came from them, in any chunking, and get one description per
// frame: direction, servo ID, instruction (FF FF / D5 5D) or Modbus function code, the control
// table's field names (and values where the frame carries them) for the addresses it reads or
// writes, the status byte's bits, checksum/CRC errors, noise, and retries (the same request sent
// again with no answer in between). Field names come from the servos' own tables (tables.h),
// never from a second list.
#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"
#include "protocol/bus_protocol.h"
#include "protocol/packet.h"
#include "protocol/stream_decoder.h"

namespace sms::modbus_map {

enum class WireDirection : std::uint8_t { ToServos, FromServos };
std::string_view to_string(WireDirection direction);  // "to_servos", "from_servos"

// The control table (and byte order) of each servo ID on one bus, for field names and values.
struct ServoTables {
  std::array<const TableSpec*, 256> table{};
  std::array<ByteOrder, 256> order{};
  void set(std::uint8_t id, const TableSpec& spec, ByteOrder byte_order) {
    table[id] = &spec;
    order[id] = byte_order;
  }
};

enum class FrameKind : std::uint8_t {
  Request,  // a valid frame to the servos
  Answer,   // a valid frame from a servo
  Damaged,  // a whole frame with a wrong checksum or CRC, an impossible LEN, or one cut short
  Noise,    // bytes that made no frame (echo tails, garbage, a collision)
};
std::string_view to_string(FrameKind kind);  // "request", "answer", "damaged", "noise"

struct FieldValue {
  std::string name;  // the table's field name; "address N" where no field starts there
  std::uint16_t address = 0;
  std::optional<std::int32_t> value;  // as a Modbus client sees it; empty where the frame carries none (READ)
  std::optional<std::uint8_t> servo;  // SYNC WRITE / SYNC READ: whose field
};

struct FrameDescription {
  WireDirection direction = WireDirection::ToServos;
  FrameKind kind = FrameKind::Request;
  std::optional<std::uint8_t> servo;  // the addressed or answering ID (0xFE / 0 broadcast)
  std::vector<std::uint8_t> servos;   // every servo the frame concerns (SYNC members), for filters
  std::string instruction;  // "WRITE", "SYNC READ", "write_multiple_registers", ...; an answer names its request's
  std::optional<std::uint8_t> code;  // instruction or function code as sent
  std::vector<FieldValue> fields;
  std::optional<std::uint8_t> status;         // the ERROR/status byte of a packet answer
  std::vector<std::string_view> status_bits;  // its bits by name: "overload", "instruction", ...
  std::string error;                          // checksum/CRC error, noise, Modbus exception: what, in words
  bool retry = false;                         // the same request again, with no answer in between
  protocol::Bytes bytes;                      // the frame as on the wire
};

// Describes the frames of one bus. One per reader: it keeps the partial frames of each
// direction and the last request (to name an answer's fields).
class FrameDescriber {
 public:
  FrameDescriber(protocol::BusProtocol protocol, const ServoTables& tables);

  // Bytes as recorded in one piece (one write, one read); returns the frames they completed.
  std::vector<FrameDescription> feed(WireDirection direction, std::span<const std::uint8_t> bytes);
  // Forget partial frames and the last request (a gap in the recording).
  void reset();

 private:
  std::vector<FrameDescription> feed_packets(WireDirection direction, std::span<const std::uint8_t> bytes);
  std::vector<FrameDescription> feed_rtu(WireDirection direction, std::span<const std::uint8_t> bytes);
  FrameDescription describe_packet_request(const protocol::Packet& packet) const;
  FrameDescription describe_packet_answer(const protocol::Packet& packet) const;
  void flush_rtu(WireDirection direction, std::vector<FrameDescription>& frames);
  FrameDescription describe_rtu(WireDirection direction, std::span<const std::uint8_t> frame,
                                std::size_t expected_size);
  FrameDescription describe_rtu_request(std::span<const std::uint8_t> frame) const;
  FrameDescription describe_rtu_answer(std::span<const std::uint8_t> frame) const;
  void note_request(const protocol::Bytes& bytes, FrameDescription& description);

  protocol::BusProtocol protocol_;
  const ServoTables& tables_;
  protocol::StreamDecoder to_servos_;
  protocol::StreamDecoder from_servos_;
  std::optional<protocol::Packet> last_packet_request_;
  protocol::Bytes last_rtu_request_;
  protocol::Bytes last_request_bytes_;
  bool answered_since_request_ = true;
  std::array<std::size_t, 2> damaged_tail_{};
  std::array<protocol::Bytes, 2> rtu_pending_{};  // per direction: an RTU frame not yet whole  // per direction: bytes
                                                  // of a damaged frame still to come back as skipped
};

}  // namespace sms::modbus_map
