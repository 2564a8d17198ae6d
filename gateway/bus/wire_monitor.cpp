#include "gateway/bus/wire_monitor.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cstdio>
#include <cstring>

#include "gateway/bus/bus_engine.h"
#include "modbus_map/tables.h"
#include "protocol/hex_text.h"
#include "protocol/pcapng.h"

namespace sms::gateway {
namespace {

std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

void append_escaped(std::string& out, std::string_view text) {
  out += '"';
  for (const char c : text) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char escaped[8];
          std::snprintf(escaped, sizeof escaped, "\\u%04x", static_cast<unsigned>(static_cast<unsigned char>(c)));
          out += escaped;
        } else {
          out += c;
        }
    }
  }
  out += '"';
}

// What a pcapng packet's comment says beyond the bytes: the error, the retry.
std::string packet_comment(const modbus_map::FrameDescription& frame) {
  std::string comment = frame.error;
  if (frame.retry) comment += comment.empty() ? "retry" : "; retry";
  return comment;
}

}  // namespace

WireMonitor::WireMonitor(std::string bus_name, protocol::BusProtocol protocol, const modbus_map::ServoTables& tables,
                         std::size_t records)
    : bus_name_(std::move(bus_name)),
      protocol_(protocol),
      tables_(tables),
      ring_(std::bit_ceil(std::max<std::size_t>(records, 16))),
      mask_(ring_.size() - 1) {}

std::shared_ptr<WireMonitor> WireMonitor::for_bus(const BusSettings& settings, std::size_t records) {
  modbus_map::ServoTables tables;
  for (const auto& servo : settings.servos) {
    tables.set(servo.servo_id, modbus_map::table(servo.table), servo.byte_order);
  }
  return std::make_shared<WireMonitor>(settings.name, settings.protocol, tables, records);
}

void WireMonitor::record(WireDirection direction, std::span<const std::uint8_t> bytes) noexcept {
  record_at(direction, bytes, now_ns());
}

void WireMonitor::record_at(WireDirection direction, std::span<const std::uint8_t> bytes,
                            std::int64_t time_ns) noexcept {
  if (bytes.empty()) return;
  // A piece longer than the whole ring keeps its tail.
  const std::size_t limit = ring_.size() * kRecordBytes;
  if (bytes.size() > limit) bytes = bytes.last(limit);
  const std::lock_guard lock(mutex_);
  std::size_t in_chunk = 0;
  while (!bytes.empty()) {
    Record& slot = ring_[next_ & mask_];
    const std::size_t length = std::min(bytes.size(), kRecordBytes);
    slot.time_ns = time_ns;
    slot.direction = static_cast<std::uint8_t>(direction);
    // A long piece becomes chunks of at most kMaxChunkRecords (the decoders take a stream, so
    // where one chunk ends and the next begins changes no frame).
    slot.continues = in_chunk != 0;
    in_chunk = (in_chunk + 1) % kMaxChunkRecords;
    slot.length = static_cast<std::uint8_t>(length);
    std::memcpy(slot.data.data(), bytes.data(), length);
    bytes = bytes.subspan(length);
    ++next_;
  }
}

std::uint64_t WireMonitor::oldest_sequence() const {
  const std::lock_guard lock(mutex_);
  return next_ > ring_.size() ? next_ - ring_.size() : 0;
}

std::uint64_t WireMonitor::next_sequence() const {
  const std::lock_guard lock(mutex_);
  return next_;
}

WireChunks WireMonitor::chunks_since(std::uint64_t sequence, std::size_t max_records) const {
  WireChunks result;
  // The records are copied out under the lock (no allocation there: the room is made first) and
  // joined into chunks after it, so a reader holds the bus thread up for a copy at most.
  max_records = std::clamp<std::size_t>(max_records, 1, ring_.size());
  std::vector<Record> copied;
  copied.reserve(max_records + kMaxChunkRecords);
  std::uint64_t first_copied = 0;
  {
    const std::lock_guard lock(mutex_);
    const std::uint64_t oldest = next_ > ring_.size() ? next_ - ring_.size() : 0;
    if (sequence < oldest) {
      result.missed = oldest - sequence;
      sequence = oldest;
    }
    sequence = std::min(sequence, next_);
    // The rest of a chunk whose beginning was overwritten (or asked for in the middle) is no use.
    while (sequence < next_ && ring_[sequence & mask_].continues) {
      ++sequence;
      ++result.missed;
    }
    first_copied = sequence;
    // Whole chunks only: past max_records, stop at the next chunk's start.
    while (sequence < next_ && (copied.size() < max_records || ring_[sequence & mask_].continues)) {
      copied.push_back(ring_[sequence & mask_]);
      ++sequence;
    }
  }
  result.next = sequence;
  for (std::size_t i = 0; i < copied.size(); ++i) {
    const Record& record = copied[i];
    if (!record.continues || result.chunks.empty()) {
      result.chunks.push_back({first_copied + i, record.time_ns, static_cast<WireDirection>(record.direction), {}});
    }
    auto& bytes = result.chunks.back().bytes;
    bytes.insert(bytes.end(), record.data.begin(), record.data.begin() + record.length);
  }
  return result;
}

protocol::Bytes WireMonitor::pcapng() const {
  protocol::pcapng::Writer writer("sms-gateway bus monitor");
  const bool rtu = protocol_ == protocol::BusProtocol::ModbusRtu;
  const std::uint32_t interface =
      writer.add_interface(rtu ? protocol::pcapng::kLinkTypeModbusRtu : protocol::pcapng::kLinkTypePacketBus, bus_name_,
                           "sms-gateway bus '" + bus_name_ + "' (" + std::string(protocol::to_string(protocol_)) + ")");
  modbus_map::FrameDescriber describer(protocol_, tables_);
  const WireChunks recorded = chunks_since(0, ring_.size());
  for (const WireChunk& chunk : recorded.chunks) {
    for (const auto& frame : describer.feed(chunk.direction, chunk.bytes)) {
      if (frame.bytes.empty()) continue;  // noise the decoder skipped without keeping its bytes
      const auto direction = frame.direction == WireDirection::ToServos ? protocol::pcapng::Direction::Outbound
                                                                        : protocol::pcapng::Direction::Inbound;
      writer.add_packet(interface, static_cast<std::uint64_t>(chunk.time_ns / 1000), direction, frame.bytes,
                        packet_comment(frame));
    }
  }
  return writer.take();
}

bool MonitorFilter::accepts(const modbus_map::FrameDescription& frame) const {
  using modbus_map::FrameKind;
  switch (frame.kind) {
    case FrameKind::Request:
      if (!requests) return false;
      break;
    case FrameKind::Answer:
      if (!answers) return false;
      break;
    case FrameKind::Damaged:
    case FrameKind::Noise:
      if (!errors) return false;
      break;
  }
  if (!servo) return true;
  return std::find(frame.servos.begin(), frame.servos.end(), *servo) != frame.servos.end();
}

MonitorReader::MonitorReader(std::shared_ptr<const WireMonitor> monitor, Start start)
    : monitor_(std::move(monitor)),
      describer_(monitor_->protocol(), monitor_->tables()),
      next_(start == Start::Oldest ? monitor_->oldest_sequence() : monitor_->next_sequence()) {}

MonitorReader::MonitorReader(std::shared_ptr<const WireMonitor> monitor, std::uint64_t sequence)
    : monitor_(std::move(monitor)), describer_(monitor_->protocol(), monitor_->tables()), next_(sequence) {}

MonitorBatch MonitorReader::poll(std::size_t max_records, const MonitorFilter& filter) {
  MonitorBatch batch;
  WireChunks recorded = monitor_->chunks_since(next_, max_records);
  if (recorded.missed > 0) {
    batch.dropped = recorded.missed;
    monitor_->count_dropped(recorded.missed);
    describer_.reset();  // the partial frames and the last request are from before the gap
  }
  for (WireChunk& chunk : recorded.chunks) {
    for (auto& frame : describer_.feed(chunk.direction, chunk.bytes)) {
      if (!filter.accepts(frame)) continue;
      batch.frames.push_back({chunk.sequence, chunk.time_ns, std::move(frame)});
    }
  }
  next_ = recorded.next;
  batch.next = next_;
  return batch;
}

std::string to_json(std::string_view bus_name, const MonitorBatch& batch) {
  std::string out = "{\"bus\":";
  append_escaped(out, bus_name);
  out += ",\"next\":" + std::to_string(batch.next) + ",\"dropped\":" + std::to_string(batch.dropped) + ",\"frames\":[";
  bool first_frame = true;
  for (const MonitoredFrame& monitored : batch.frames) {
    const modbus_map::FrameDescription& frame = monitored.frame;
    if (!first_frame) out += ',';
    first_frame = false;
    out += "{\"seq\":" + std::to_string(monitored.sequence);
    out += ",\"time_us\":" + std::to_string(monitored.time_ns / 1000);
    out += ",\"dir\":";
    append_escaped(out, modbus_map::to_string(frame.direction));
    out += ",\"kind\":";
    append_escaped(out, modbus_map::to_string(frame.kind));
    out += ",\"servo\":" + (frame.servo ? std::to_string(*frame.servo) : std::string("null"));
    out += ",\"servos\":[";
    for (std::size_t i = 0; i < frame.servos.size(); ++i) {
      if (i > 0) out += ',';
      out += std::to_string(frame.servos[i]);
    }
    out += "],\"instruction\":";
    append_escaped(out, frame.instruction);
    out += ",\"code\":" + (frame.code ? std::to_string(*frame.code) : std::string("null"));
    out += ",\"fields\":[";
    for (std::size_t i = 0; i < frame.fields.size(); ++i) {
      const auto& field = frame.fields[i];
      if (i > 0) out += ',';
      out += "{\"name\":";
      append_escaped(out, field.name);
      out += ",\"address\":" + std::to_string(field.address);
      if (field.value) out += ",\"value\":" + std::to_string(*field.value);
      if (field.servo) out += ",\"servo\":" + std::to_string(*field.servo);
      out += '}';
    }
    out += "],\"status\":" + (frame.status ? std::to_string(*frame.status) : std::string("null"));
    out += ",\"status_bits\":[";
    for (std::size_t i = 0; i < frame.status_bits.size(); ++i) {
      if (i > 0) out += ',';
      append_escaped(out, frame.status_bits[i]);
    }
    out += "],\"error\":";
    append_escaped(out, frame.error);
    out += ",\"retry\":";
    out += frame.retry ? "true" : "false";
    out += ",\"bytes\":";
    append_escaped(out, protocol::hex_bytes(frame.bytes));
    out += '}';
  }
  out += "]}";
  return out;
}

}  // namespace sms::gateway
