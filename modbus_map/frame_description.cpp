#include "modbus_map/frame_description.h"

#include <algorithm>
#include <cstdio>

#include "modbus_map/status_bits.h"
#include "modbus_map/tables.h"
#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/hex_text.h"
#include "protocol/instructions.h"
#include "protocol/modbus_pdu.h"
#include "protocol/modbus_rtu.h"

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;
using protocol::Bytes;

const protocol::PacketFormat& packet_format(BusProtocol protocol) {
  return protocol == BusProtocol::D55d ? protocol::kD55dFormat : protocol::kFeetechFormat;
}

std::string instruction_name(BusProtocol protocol, std::uint8_t code) {
  const auto name = protocol == BusProtocol::D55d ? protocol::d55d::instruction_name(code)
                                                  : protocol::feetech::instruction_name(code);
  return name ? std::string(*name) : "instruction " + protocol::hex_number(code);
}

std::string function_name(std::uint8_t code) {
  const auto* function = protocol::find_modbus_function(code);
  return function != nullptr ? std::string(function->name) : "function " + protocol::hex_number(code);
}

// The table to name a broadcast's fields by: the lowest ID's (a bus speaks one protocol; its
// tables differ little where broadcasts write).
const TableSpec* table_for(const ServoTables& tables, std::uint8_t id, std::uint8_t& order_id) {
  order_id = id;
  if (tables.table[id] != nullptr) return tables.table[id];
  for (std::size_t other = 0; other < tables.table.size(); ++other) {
    if (tables.table[other] != nullptr) {
      order_id = static_cast<std::uint8_t>(other);
      return tables.table[other];
    }
  }
  return nullptr;
}

// The fields in [address, address + count) (count in the table's addresses), with their values
// when `data` holds the range's bytes.
void add_fields(std::vector<FieldValue>& out, const ServoTables& tables, std::uint8_t id, std::uint16_t address,
                std::size_t count, std::optional<std::span<const std::uint8_t>> data,
                std::optional<std::uint8_t> member = std::nullopt) {
  std::uint8_t order_id = id;
  const TableSpec* spec = table_for(tables, id, order_id);
  const std::size_t before = out.size();
  if (spec != nullptr) {
    const std::size_t per_address = bytes_per_address(spec->addressing);
    const std::size_t end = std::size_t{address} + count;
    for (std::size_t at = address; at < end;) {
      const FieldSpec* field = field_at(*spec, static_cast<std::uint16_t>(at));
      if (field == nullptr) {
        if (const FieldSpec* covering = field_covering(*spec, static_cast<std::uint16_t>(at));
            covering != nullptr && at == address) {
          out.push_back({std::string(covering->name) + " (high byte)", static_cast<std::uint16_t>(at), {}, member});
        }
        ++at;
        continue;
      }
      const std::size_t span = address_span(spec->addressing, *field);
      FieldValue value{std::string(field->name), field->addr, {}, member};
      const std::size_t offset = (at - address) * per_address;
      if (data && at + span <= end && offset + field->size <= data->size()) {
        const auto raw = load_raw(data->subspan(offset, field->size), field->size, tables.order[order_id]);
        value.value = decode_value(*field, raw);
      } else if (at + span > end) {
        value.name += " (low byte)";
      }
      out.push_back(std::move(value));
      at += span;
    }
  }
  if (out.size() == before) {
    out.push_back(
        {"address " + std::to_string(address) + (count > 1 ? "+" + std::to_string(count) : ""), address, {}, member});
  }
}

std::uint16_t be16(std::span<const std::uint8_t> bytes, std::size_t at) {
  return static_cast<std::uint16_t>(bytes[at] << 8 | bytes[at + 1]);
}

// How long the RTU frame starting at `frame` is, from its function code (Modbus over serial
// line v1.02: the length follows from the PDU for the functions the servos know); nullopt: the
// whole piece (an unknown function), or too few bytes to tell.
std::optional<std::size_t> rtu_frame_size(WireDirection direction, std::span<const std::uint8_t> frame) {
  namespace fc = protocol::function_code;
  if (frame.size() < 2) return std::nullopt;
  const std::uint8_t function = frame[1];
  const auto counted = [&](std::size_t at, std::size_t fixed) -> std::optional<std::size_t> {
    if (frame.size() <= at) return std::nullopt;
    return fixed + frame[at];
  };
  if (direction == WireDirection::ToServos) {
    switch (function) {
      case fc::kReadCoils:
      case fc::kReadDiscreteInputs:
      case fc::kReadHoldingRegisters:
      case fc::kReadInputRegisters:
      case fc::kWriteSingleCoil:
      case fc::kWriteSingleRegister: return 8;
      case fc::kWriteMultipleCoils:
      case fc::kWriteMultipleRegisters: return counted(6, 9);
      case fc::kReadWriteMultipleRegisters: return counted(10, 13);
      case fc::kReportServerId: return 4;
      default: return std::nullopt;
    }
  }
  if (function & fc::kExceptionBit) return 5;
  switch (function) {
    case fc::kReadCoils:
    case fc::kReadDiscreteInputs:
    case fc::kReadHoldingRegisters:
    case fc::kReadInputRegisters:
    case fc::kReadWriteMultipleRegisters:
    case fc::kReportServerId: return counted(2, 5);
    case fc::kWriteSingleCoil:
    case fc::kWriteSingleRegister:
    case fc::kWriteMultipleCoils:
    case fc::kWriteMultipleRegisters: return 8;
    default: return std::nullopt;
  }
}

bool crc_ok(std::span<const std::uint8_t> frame) {
  return frame.size() >= protocol::rtu::kMinAduSize &&
         protocol::rtu::crc16(frame.first(frame.size() - 2)) ==
             static_cast<std::uint16_t>(frame[frame.size() - 2] | frame[frame.size() - 1] << 8);
}

FrameDescription noise(WireDirection direction, std::span<const std::uint8_t> bytes, std::size_t count) {
  FrameDescription description;
  description.direction = direction;
  description.kind = FrameKind::Noise;
  description.error = std::to_string(count) + " byte" + (count == 1 ? "" : "s") + " that made no frame";
  description.bytes.assign(bytes.begin(), bytes.end());
  return description;
}

// What every RTU frame says first: direction, kind, the slave (its servo) and the function,
// named by `named_function` (an exception answer by the function it answers).
FrameDescription rtu_frame(std::span<const std::uint8_t> frame, WireDirection direction, FrameKind kind,
                           std::uint8_t named_function) {
  FrameDescription description;
  description.direction = direction;
  description.kind = kind;
  description.servo = frame[0];
  description.servos = {frame[0]};
  description.code = frame[1];
  description.instruction = function_name(named_function);
  return description;
}

}  // namespace

std::string_view to_string(WireDirection direction) {
  return direction == WireDirection::ToServos ? "to_servos" : "from_servos";
}

std::string_view to_string(FrameKind kind) {
  switch (kind) {
    case FrameKind::Request: return "request";
    case FrameKind::Answer: return "answer";
    case FrameKind::Damaged: return "damaged";
    case FrameKind::Noise: return "noise";
  }
  return "?";
}

FrameDescriber::FrameDescriber(BusProtocol protocol, const ServoTables& tables)
    : protocol_(protocol),
      tables_(tables),
      to_servos_(packet_format(protocol)),
      from_servos_(packet_format(protocol)) {}

void FrameDescriber::reset() {
  to_servos_.reset();
  from_servos_.reset();
  last_packet_request_.reset();
  last_rtu_request_.clear();
  last_request_bytes_.clear();
  answered_since_request_ = true;
  damaged_tail_ = {};
  rtu_pending_ = {};
}

std::vector<FrameDescription> FrameDescriber::feed(WireDirection direction, std::span<const std::uint8_t> bytes) {
  return protocol_ == BusProtocol::ModbusRtu ? feed_rtu(direction, bytes) : feed_packets(direction, bytes);
}

void FrameDescriber::note_request(const Bytes& bytes, FrameDescription& description) {
  const bool broadcast = description.servo && (*description.servo == protocol::kBroadcastId ||
                                               (protocol_ == BusProtocol::ModbusRtu && *description.servo == 0));
  description.retry = !broadcast && !answered_since_request_ && bytes == last_request_bytes_;
  last_request_bytes_ = bytes;
  answered_since_request_ = broadcast;
}

// --- FF FF / D5 5D --------------------------------------------------------------------------------

std::vector<FrameDescription> FrameDescriber::feed_packets(WireDirection direction,
                                                           std::span<const std::uint8_t> bytes) {
  const protocol::PacketFormat& format = packet_format(protocol_);
  protocol::StreamDecoder& decoder = direction == WireDirection::ToServos ? to_servos_ : from_servos_;
  decoder.feed(bytes);
  std::vector<FrameDescription> frames;
  std::size_t& tail = damaged_tail_[static_cast<std::size_t>(direction)];
  while (auto event = decoder.next()) {
    // The decoder resynchronises one byte past a damaged frame's header: that frame's bytes come
    // back as skipped bytes, already shown with the damaged frame.
    const std::size_t own_tail = std::min(tail, event->skipped_before);
    tail = 0;
    if (event->skipped_before > own_tail) {
      frames.push_back(noise(direction, {}, event->skipped_before - own_tail));
    }
    Bytes raw;
    if (event->kind == protocol::DecodeEvent::Kind::LengthError) {
      FrameDescription damaged;
      damaged.direction = direction;
      damaged.kind = FrameKind::Damaged;
      damaged.servo = event->packet.id;
      damaged.servos = {event->packet.id};
      damaged.error = "impossible LEN (below 2): not a frame";
      damaged.bytes = {format.header[0], format.header[1], event->packet.id};
      tail = damaged.bytes.size() + 1;  // and its LEN
      frames.push_back(std::move(damaged));
      continue;
    }
    raw = protocol::encode(format, event->packet);
    if (event->kind == protocol::DecodeEvent::Kind::ChecksumError) {
      const std::uint8_t expected = raw.back();
      raw.back() = event->received_checksum;
      FrameDescription damaged = direction == WireDirection::ToServos ? describe_packet_request(event->packet)
                                                                      : describe_packet_answer(event->packet);
      damaged.kind = FrameKind::Damaged;
      damaged.error = "checksum error: " + protocol::hex_number(event->received_checksum) + " received, " +
                      protocol::hex_number(expected) + " expected";
      damaged.bytes = std::move(raw);
      tail = damaged.bytes.size();
      frames.push_back(std::move(damaged));
      continue;
    }
    if (direction == WireDirection::ToServos) {
      FrameDescription request = describe_packet_request(event->packet);
      note_request(raw, request);
      last_packet_request_ = event->packet;
      request.bytes = std::move(raw);
      frames.push_back(std::move(request));
    } else {
      FrameDescription answer = describe_packet_answer(event->packet);
      answered_since_request_ = true;
      answer.bytes = std::move(raw);
      frames.push_back(std::move(answer));
    }
  }
  return frames;
}

FrameDescription FrameDescriber::describe_packet_request(const protocol::Packet& packet) const {
  namespace common = protocol::common;
  FrameDescription description;
  description.direction = WireDirection::ToServos;
  description.kind = FrameKind::Request;
  description.servo = packet.id;
  description.servos = {packet.id};
  description.code = packet.code;
  description.instruction = instruction_name(protocol_, packet.code);
  switch (packet.code) {
    case common::kRead:
      if (const auto read = protocol::parse_read(packet.params)) {
        add_fields(description.fields, tables_, packet.id, read->address, read->count, std::nullopt);
      }
      break;
    case common::kWrite:
    case common::kRegWrite:
      if (const auto write = protocol::parse_write(packet.params)) {
        add_fields(description.fields, tables_, packet.id, write->address, write->data.size(),
                   std::span<const std::uint8_t>(write->data));
      }
      break;
    case common::kSyncWrite:
      if (const auto sync = protocol::parse_sync_write(packet.params)) {
        description.servos.clear();
        for (const auto& entry : sync->entries) {
          description.servos.push_back(entry.id);
          add_fields(description.fields, tables_, entry.id, sync->address, sync->length,
                     std::span<const std::uint8_t>(entry.data), entry.id);
        }
      }
      break;
    default:
      if (protocol_ == BusProtocol::Feetech && packet.code == protocol::feetech::kSyncRead) {
        if (const auto sync = protocol::feetech::parse_sync_read(packet.params); sync && !sync->ids.empty()) {
          description.servos = sync->ids;
          add_fields(description.fields, tables_, sync->ids.front(), sync->address, sync->count, std::nullopt);
        }
      }
      break;
  }
  return description;
}

FrameDescription FrameDescriber::describe_packet_answer(const protocol::Packet& packet) const {
  FrameDescription description;
  description.direction = WireDirection::FromServos;
  description.kind = FrameKind::Answer;
  description.servo = packet.id;
  description.servos = {packet.id};
  description.status = packet.code;
  for (const auto& bit : status_bits(protocol_ == BusProtocol::D55d ? TableId::D55d : TableId::Sts)) {
    if (packet.code & bit.mask) description.status_bits.push_back(bit.name);
  }
  if (!last_packet_request_) {
    description.instruction = "answer";
    return description;
  }
  const protocol::Packet& request = *last_packet_request_;
  description.instruction = instruction_name(protocol_, request.code);
  if (request.code == protocol::common::kRead && (request.id == packet.id || request.id == protocol::kBroadcastId)) {
    if (const auto read = protocol::parse_read(request.params); read && packet.params.size() == read->count) {
      add_fields(description.fields, tables_, packet.id, read->address, read->count,
                 std::span<const std::uint8_t>(packet.params));
    }
  } else if (protocol_ == BusProtocol::Feetech && request.code == protocol::feetech::kSyncRead) {
    const auto sync = protocol::feetech::parse_sync_read(request.params);
    if (sync && packet.params.size() == sync->count &&
        std::find(sync->ids.begin(), sync->ids.end(), packet.id) != sync->ids.end()) {
      add_fields(description.fields, tables_, packet.id, sync->address, sync->count,
                 std::span<const std::uint8_t>(packet.params), packet.id);
    }
  }
  return description;
}

// --- Modbus RTU -------------------------------------------------------------------------------------

std::vector<FrameDescription> FrameDescriber::feed_rtu(WireDirection direction, std::span<const std::uint8_t> bytes) {
  std::vector<FrameDescription> frames;
  // The line turned around: what the other direction left unfinished will not be finished.
  const auto other = direction == WireDirection::ToServos ? WireDirection::FromServos : WireDirection::ToServos;
  flush_rtu(other, frames);
  Bytes& pending = rtu_pending_[static_cast<std::size_t>(direction)];
  pending.insert(pending.end(), bytes.begin(), bytes.end());
  std::size_t used = 0;
  while (pending.size() - used >= 2) {
    const auto rest = std::span<const std::uint8_t>(pending).subspan(used);
    // An unknown function's frame ends with the piece it came in (the silence is not recorded).
    const std::size_t size =
        std::min(rtu_frame_size(direction, rest).value_or(rest.size()), protocol::rtu::kMaxAduSize);
    if (rest.size() < size) break;
    frames.push_back(describe_rtu(direction, rest.first(size), size));
    used += size;
  }
  pending.erase(pending.begin(), pending.begin() + static_cast<std::ptrdiff_t>(used));
  return frames;
}

void FrameDescriber::flush_rtu(WireDirection direction, std::vector<FrameDescription>& frames) {
  Bytes& pending = rtu_pending_[static_cast<std::size_t>(direction)];
  if (pending.empty()) return;
  if (pending.size() < protocol::rtu::kMinAduSize) {
    frames.push_back(noise(direction, pending, pending.size()));
  } else {
    const auto size = rtu_frame_size(direction, pending).value_or(pending.size());
    frames.push_back(describe_rtu(direction, pending, size));
  }
  pending.clear();
}

FrameDescription FrameDescriber::describe_rtu(WireDirection direction, std::span<const std::uint8_t> frame,
                                              std::size_t expected_size) {
  FrameDescription description =
      direction == WireDirection::ToServos ? describe_rtu_request(frame) : describe_rtu_answer(frame);
  if (frame.size() < expected_size) {
    description.kind = FrameKind::Damaged;
    description.error =
        "cut short: " + std::to_string(frame.size()) + " of " + std::to_string(expected_size) + " bytes";
    description.fields.clear();
  } else if (!crc_ok(frame)) {
    description.kind = FrameKind::Damaged;
    description.error = "CRC error";
    description.fields.clear();
  } else if (direction == WireDirection::ToServos) {
    last_rtu_request_.assign(frame.begin(), frame.end());
    note_request(last_rtu_request_, description);
  } else {
    answered_since_request_ = true;
  }
  description.bytes.assign(frame.begin(), frame.end());
  return description;
}

FrameDescription FrameDescriber::describe_rtu_request(std::span<const std::uint8_t> frame) const {
  namespace fc = protocol::function_code;
  FrameDescription description = rtu_frame(frame, WireDirection::ToServos, FrameKind::Request, frame[1]);
  const std::uint8_t slave = frame[0];
  const std::uint8_t function = frame[1];
  const auto pdu = frame.first(frame.size() - 2);  // slave .. last data byte
  switch (function) {
    case fc::kReadHoldingRegisters:
    case fc::kReadInputRegisters:
      if (pdu.size() >= 6) add_fields(description.fields, tables_, slave, be16(pdu, 2), be16(pdu, 4), std::nullopt);
      break;
    case fc::kWriteSingleRegister:
      if (pdu.size() >= 6) add_fields(description.fields, tables_, slave, be16(pdu, 2), 1, pdu.subspan(4, 2));
      break;
    case fc::kWriteMultipleRegisters:
      if (pdu.size() >= 7 && pdu.size() >= 7u + pdu[6]) {
        add_fields(description.fields, tables_, slave, be16(pdu, 2), be16(pdu, 4), pdu.subspan(7, pdu[6]));
      }
      break;
    case fc::kWriteSingleCoil:
      if (pdu.size() >= 6) {
        description.fields.push_back(
            {"coil " + std::to_string(be16(pdu, 2)), be16(pdu, 2), be16(pdu, 4) == 0xFF00 ? 1 : 0, std::nullopt});
      }
      break;
    default: break;
  }
  return description;
}

FrameDescription FrameDescriber::describe_rtu_answer(std::span<const std::uint8_t> frame) const {
  namespace fc = protocol::function_code;
  FrameDescription description =
      rtu_frame(frame, WireDirection::FromServos, FrameKind::Answer, frame[1] & ~fc::kExceptionBit);
  const std::uint8_t slave = frame[0];
  const std::uint8_t function = frame[1];
  const auto pdu = frame.first(frame.size() - 2);
  if (function & fc::kExceptionBit) {
    if (pdu.size() >= 3) {
      description.error =
          "exception " + protocol::hex_number(pdu[2]) + " " + std::string(protocol::modbus_exception_name(pdu[2]));
    }
    return description;
  }
  const auto& request = last_rtu_request_;
  const bool answers_request = request.size() >= 6 && request[0] == slave && request[1] == function;
  switch (function) {
    case fc::kReadHoldingRegisters:
    case fc::kReadInputRegisters:
      if (answers_request && pdu.size() >= 3 && pdu.size() == 3u + pdu[2] && pdu[2] == 2 * be16(request, 4)) {
        add_fields(description.fields, tables_, slave, be16(request, 2), be16(request, 4), pdu.subspan(3));
      }
      break;
    case fc::kWriteSingleRegister:
      if (pdu.size() >= 6) add_fields(description.fields, tables_, slave, be16(pdu, 2), 1, pdu.subspan(4, 2));
      break;
    case fc::kWriteMultipleRegisters:
      if (pdu.size() >= 6) add_fields(description.fields, tables_, slave, be16(pdu, 2), be16(pdu, 4), std::nullopt);
      break;
    default: break;
  }
  return description;
}

}  // namespace sms::modbus_map
