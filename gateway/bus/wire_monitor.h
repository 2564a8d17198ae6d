#pragma once
// The bus monitor (docs/MONITOR.md): every byte a bus writes to its line and reads from it,
// copied with its time into a bounded ring, and read back as described frames (for the console's
// live view) or as a pcapng capture (for Wireshark).
//
// The bus thread only records: one short lock, a copy into preallocated records, never an
// allocation, never a wait for a reader. The ring holds the latest `records` records of up to
// kRecordBytes bytes each (a longer write or read takes several, marked as continuing); when it
// is full the oldest are overwritten. A reader that fell behind is told how many records it
// missed (and those are counted in dropped_total(), sms_gateway_monitor_dropped_total): the
// bus is never slowed for a slow browser. Decoding and description (modbus_map/
// frame_description.h) happen on the reader's thread.
#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/frame_description.h"
#include "protocol/bus_protocol.h"
#include "protocol/packet.h"

namespace sms::gateway {

struct BusSettings;
using modbus_map::WireDirection;

// One write or read as recorded: the bytes of one record() call (of a very long one, up to
// kMaxChunkRecords records of it).
struct WireChunk {
  std::uint64_t sequence = 0;  // of its first record
  std::int64_t time_ns = 0;    // system clock, since 1970-01-01 UTC
  WireDirection direction = WireDirection::ToServos;
  protocol::Bytes bytes;
};

struct WireChunks {
  std::vector<WireChunk> chunks;
  std::uint64_t next = 0;    // the sequence to ask for next
  std::uint64_t missed = 0;  // records between the sequence asked for and the oldest still held
};

class WireMonitor {
 public:
  static constexpr std::size_t kRecordBytes = 48;
  // Records one chunk takes at most (3 KiB; a longer piece is recorded as several chunks).
  static constexpr std::size_t kMaxChunkRecords = 64;
  // 8192 records of 64 bytes: 512 KiB per bus; at a 100 Hz poll cycle of six servos (about 7 records a
  // cycle) some ten seconds of history.
  static constexpr std::size_t kDefaultRecords = 8192;

  // `records` is rounded up to a power of two (at least 16).
  WireMonitor(std::string bus_name, protocol::BusProtocol protocol, const modbus_map::ServoTables& tables,
              std::size_t records = kDefaultRecords);
  // A monitor for the bus `settings` describe: its name, protocol, and each servo's table.
  static std::shared_ptr<WireMonitor> for_bus(const BusSettings& settings, std::size_t records = kDefaultRecords);

  // --- the bus thread ---
  // `bytes` went to the servos (ToServos) or came from the line (FromServos), just now.
  void record(WireDirection direction, std::span<const std::uint8_t> bytes) noexcept;
  void record_at(WireDirection direction, std::span<const std::uint8_t> bytes, std::int64_t time_ns) noexcept;

  // --- any thread ---
  // The whole chunks recorded from `sequence` on: `max_records` records (at most the ring's
  // size), plus the rest of the chunk the last of them belongs to. A sequence older than the
  // oldest record held starts at the oldest.
  WireChunks chunks_since(std::uint64_t sequence, std::size_t max_records) const;
  std::uint64_t oldest_sequence() const;
  std::uint64_t next_sequence() const;
  // Records readers missed because the ring had overwritten them (every reader's, summed).
  std::uint64_t dropped_total() const { return dropped_.load(std::memory_order_relaxed); }
  void count_dropped(std::uint64_t records) const { dropped_.fetch_add(records, std::memory_order_relaxed); }
  // The ring's contents as a pcapng capture: one interface (LINKTYPE_USER0 packet buses,
  // USER1 Modbus RTU; docs/MONITOR.md), one packet per frame with its direction; damaged frames
  // and retries carry a comment.
  protocol::Bytes pcapng() const;

  const std::string& bus_name() const { return bus_name_; }
  protocol::BusProtocol protocol() const { return protocol_; }
  const modbus_map::ServoTables& tables() const { return tables_; }
  std::size_t capacity() const { return ring_.size(); }

 private:
  struct Record {
    std::int64_t time_ns = 0;
    std::uint8_t direction = 0;
    bool continues = false;  // more bytes of the chunk the record before began
    std::uint8_t length = 0;
    std::array<std::uint8_t, kRecordBytes> data{};
  };
  static_assert(sizeof(Record) == 64, "a record is one cache line; kDefaultRecords' size counts on it");

  const std::string bus_name_;
  const protocol::BusProtocol protocol_;
  const modbus_map::ServoTables tables_;
  mutable std::mutex mutex_;
  std::vector<Record> ring_;  // a power of two long: record `s` is ring_[s & mask_]
  const std::uint64_t mask_;
  std::uint64_t next_ = 0;                         // sequence of the next record
  mutable std::atomic<std::uint64_t> dropped_{0};  // counted by readers
};

// Which frames a reader wants: one servo's (those that concern it: its requests and answers, a
// SYNC WRITE naming it), and some kinds.
struct MonitorFilter {
  std::optional<std::uint8_t> servo;
  bool requests = true;
  bool answers = true;
  bool errors = true;  // damaged frames and noise
  bool accepts(const modbus_map::FrameDescription& frame) const;
};

struct MonitoredFrame {
  std::uint64_t sequence = 0;  // of the record that completed it
  std::int64_t time_ns = 0;    // when that record was made
  modbus_map::FrameDescription frame;
};

struct MonitorBatch {
  std::vector<MonitoredFrame> frames;
  std::uint64_t next = 0;     // the reader's position after this batch
  std::uint64_t dropped = 0;  // records the ring overwrote before this reader got them (this batch)
};

// One watcher of a bus (a console WebSocket): its position in the ring and its decoder state.
class MonitorReader {
 public:
  enum class Start : std::uint8_t { Oldest, Now };
  explicit MonitorReader(std::shared_ptr<const WireMonitor> monitor, Start start = Start::Now);
  // From `sequence` on (a batch's `next`, e.g. a console page that reconnects): what was
  // overwritten since is reported as dropped by the first poll().
  MonitorReader(std::shared_ptr<const WireMonitor> monitor, std::uint64_t sequence);

  // The frames completed by up to `max_records` more records, those `filter` accepts.
  MonitorBatch poll(std::size_t max_records = 1024, const MonitorFilter& filter = {});
  std::uint64_t position() const { return next_; }

 private:
  std::shared_ptr<const WireMonitor> monitor_;
  modbus_map::FrameDescriber describer_;
  std::uint64_t next_ = 0;
};

// A batch as JSON for the console: {"bus":..,"next":..,"dropped":..,"frames":[{...}]}
// (docs/MONITOR.md lists the keys).
std::string to_json(std::string_view bus_name, const MonitorBatch& batch);

}  // namespace sms::gateway
