// The bus monitor's ring and readers (gateway/bus/wire_monitor.h): bounded, the oldest records
// overwritten, what a slow reader missed counted, sequences continuous, long writes split and
// joined again, filters, and the JSON a console forwards.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "gateway/bus/wire_monitor.h"
#include "modbus_map/tables.h"

namespace sms::gateway {
namespace {

using modbus_map::FrameKind;
using protocol::Bytes;

modbus_map::ServoTables sts_servos() {
  modbus_map::ServoTables tables;
  for (std::uint8_t id = 1; id <= 4; ++id)
    tables.set(id, modbus_map::table(modbus_map::TableId::Sts), modbus_map::ByteOrder::LowFirst);
  return tables;
}

const Bytes kPing{0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB};
const Bytes kPingAnswer{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC};

std::shared_ptr<WireMonitor> monitor(std::size_t records = 64) {
  return std::make_shared<WireMonitor>("arm", protocol::BusProtocol::Feetech, sts_servos(), records);
}

TEST(WireMonitor, RecordsAreNumberedWithoutGaps) {
  auto wire = monitor();
  EXPECT_EQ(wire->next_sequence(), 0u);
  wire->record(WireDirection::ToServos, kPing);
  wire->record(WireDirection::FromServos, kPingAnswer);
  EXPECT_EQ(wire->next_sequence(), 2u);
  const auto got = wire->chunks_since(0, 100);
  ASSERT_EQ(got.chunks.size(), 2u);
  EXPECT_EQ(got.chunks[0].sequence, 0u);
  EXPECT_EQ(got.chunks[1].sequence, 1u);
  EXPECT_EQ(got.chunks[0].bytes, kPing);
  EXPECT_EQ(got.chunks[1].direction, WireDirection::FromServos);
  EXPECT_LE(got.chunks[0].time_ns, got.chunks[1].time_ns);
  EXPECT_EQ(got.next, 2u);
  EXPECT_EQ(got.missed, 0u);
}

TEST(WireMonitor, TheRingIsBoundedAndASlowReaderIsToldWhatItMissed) {
  auto wire = monitor(16);
  MonitorReader reader(wire, MonitorReader::Start::Oldest);
  for (int i = 0; i < 40; ++i) {
    wire->record(WireDirection::ToServos, kPing);
    wire->record(WireDirection::FromServos, kPingAnswer);
  }
  EXPECT_EQ(wire->capacity(), 16u);
  EXPECT_EQ(wire->oldest_sequence(), 80u - 16u);
  const auto batch = reader.poll(1000);
  EXPECT_EQ(batch.dropped, 64u);
  EXPECT_EQ(wire->dropped_total(), 64u);
  EXPECT_EQ(batch.frames.size(), 16u);  // the eight exchanges still held
  EXPECT_EQ(batch.frames.front().sequence, 64u);
  EXPECT_EQ(batch.next, 80u);
  // Caught up: nothing missed any more.
  wire->record(WireDirection::ToServos, kPing);
  const auto next = reader.poll(1000);
  EXPECT_EQ(next.dropped, 0u);
  ASSERT_EQ(next.frames.size(), 1u);
  EXPECT_EQ(next.frames[0].sequence, 80u);
  EXPECT_EQ(wire->dropped_total(), 64u);
}

TEST(WireMonitor, AWriteLongerThanARecordTakesSeveralAndComesBackWhole) {
  auto wire = monitor(16);
  Bytes long_write(WireMonitor::kRecordBytes * 2 + 5);
  for (std::size_t i = 0; i < long_write.size(); ++i) long_write[i] = static_cast<std::uint8_t>(i);
  wire->record(WireDirection::ToServos, long_write);
  EXPECT_EQ(wire->next_sequence(), 3u);
  const auto got = wire->chunks_since(0, 100);
  ASSERT_EQ(got.chunks.size(), 1u);
  EXPECT_EQ(got.chunks[0].bytes, long_write);
  // Asked from its middle (its beginning overwritten), the rest is skipped as missed.
  const auto middle = wire->chunks_since(1, 100);
  EXPECT_TRUE(middle.chunks.empty());
  EXPECT_EQ(middle.missed, 2u);
  EXPECT_EQ(middle.next, 3u);
}

TEST(WireMonitor, AVeryLongReadIsRecordedAsSeveralChunksOfTheSameBytes) {
  auto wire = monitor(256);
  Bytes long_read(WireMonitor::kRecordBytes * (WireMonitor::kMaxChunkRecords + 6));
  for (std::size_t i = 0; i < long_read.size(); ++i) long_read[i] = static_cast<std::uint8_t>(i * 7);
  wire->record(WireDirection::FromServos, long_read);
  const auto got = wire->chunks_since(0, 1);  // one record asked for: the whole first chunk comes
  ASSERT_EQ(got.chunks.size(), 1u);
  EXPECT_EQ(got.chunks[0].bytes.size(), WireMonitor::kRecordBytes * WireMonitor::kMaxChunkRecords);
  EXPECT_EQ(got.next, WireMonitor::kMaxChunkRecords);
  const auto rest = wire->chunks_since(got.next, 100);
  ASSERT_EQ(rest.chunks.size(), 1u);
  Bytes joined = got.chunks[0].bytes;
  joined.insert(joined.end(), rest.chunks[0].bytes.begin(), rest.chunks[0].bytes.end());
  EXPECT_EQ(joined, long_read);
}

TEST(WireMonitor, BatchesStopAtWholeChunks) {
  auto wire = monitor();
  for (int i = 0; i < 10; ++i) wire->record(WireDirection::ToServos, kPing);
  const auto first = wire->chunks_since(0, 4);
  EXPECT_EQ(first.chunks.size(), 4u);
  EXPECT_EQ(first.next, 4u);
  const auto rest = wire->chunks_since(first.next, 100);
  EXPECT_EQ(rest.chunks.size(), 6u);
  EXPECT_EQ(rest.next, 10u);
}

TEST(WireMonitor, AReaderStartingNowSeesOnlyWhatComesAfter) {
  auto wire = monitor();
  wire->record(WireDirection::ToServos, kPing);
  MonitorReader reader(wire);
  EXPECT_TRUE(reader.poll().frames.empty());
  wire->record(WireDirection::FromServos, kPingAnswer);
  const auto batch = reader.poll();
  ASSERT_EQ(batch.frames.size(), 1u);
  EXPECT_EQ(batch.frames[0].frame.kind, FrameKind::Answer);
}

TEST(WireMonitor, AReaderResumesAtASequence) {
  auto wire = monitor(16);
  for (int i = 0; i < 4; ++i) wire->record(WireDirection::ToServos, kPing);
  MonitorReader resumed(wire, std::uint64_t{2});
  const auto batch = resumed.poll();
  EXPECT_EQ(batch.dropped, 0u);
  ASSERT_EQ(batch.frames.size(), 2u);
  EXPECT_EQ(batch.frames[0].sequence, 2u);
  // From a sequence the ring has overwritten since: the first poll says how many records it lost.
  for (int i = 0; i < 20; ++i) wire->record(WireDirection::ToServos, kPing);
  MonitorReader late(wire, std::uint64_t{2});
  EXPECT_EQ(late.poll().dropped, 24u - 16u - 2u);
}

TEST(WireMonitor, FiltersByServoAndKind) {
  auto wire = monitor();
  const Bytes ping2{0xFF, 0xFF, 0x02, 0x02, 0x01, 0xFA};
  const Bytes sync_write_1_and_2{0xFF, 0xFF, 0xFE, 0x0A, 0x83, 0x2A, 0x02, 0x01, 0x00, 0x08, 0x02, 0x00, 0x08, 0x35};
  wire->record(WireDirection::ToServos, kPing);
  wire->record(WireDirection::FromServos, kPingAnswer);
  wire->record(WireDirection::ToServos, ping2);
  wire->record(WireDirection::ToServos, sync_write_1_and_2);
  wire->record(WireDirection::FromServos, Bytes{0x00, 0x01, 0x02});  // noise, never followed by a frame
  wire->record(WireDirection::FromServos, Bytes{0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFD});  // damaged
  MonitorReader everything(wire, MonitorReader::Start::Oldest);
  const auto all = everything.poll();
  ASSERT_EQ(all.frames.size(), 6u);
  EXPECT_EQ(all.frames[3].frame.instruction, "SYNC WRITE");

  MonitorReader servo2(wire, MonitorReader::Start::Oldest);
  const auto of2 = servo2.poll(100, MonitorFilter{.servo = 2});
  ASSERT_EQ(of2.frames.size(), 2u);  // its PING and the SYNC WRITE naming it
  EXPECT_EQ(of2.frames[0].frame.instruction, "PING");
  EXPECT_EQ(of2.frames[1].frame.instruction, "SYNC WRITE");

  MonitorReader errors_only(wire, MonitorReader::Start::Oldest);
  const auto errors =
      errors_only.poll(100, MonitorFilter{.servo = std::nullopt, .requests = false, .answers = false, .errors = true});
  ASSERT_EQ(errors.frames.size(), 2u);  // the damaged frame (and the noise counted before it)
  EXPECT_EQ(errors.frames[0].frame.kind, FrameKind::Noise);
  EXPECT_EQ(errors.frames[1].frame.kind, FrameKind::Damaged);
}

TEST(WireMonitor, JsonOfABatch) {
  auto wire = std::make_shared<WireMonitor>("arm \"left\"", protocol::BusProtocol::Feetech, sts_servos(), 64);
  wire->record_at(WireDirection::ToServos,
                  Bytes{0xFF, 0xFF, 0x01, 0x09, 0x03, 0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03, 0xD5},
                  1'700'000'000'123'456'789);
  wire->record_at(WireDirection::FromServos, Bytes{0xFF, 0xFF, 0x01, 0x02, 0x20, 0xDC}, 1'700'000'000'124'000'000);
  MonitorReader reader(wire, MonitorReader::Start::Oldest);
  const std::string json = to_json(wire->bus_name(), reader.poll());
  EXPECT_EQ(json,
            "{\"bus\":\"arm \\\"left\\\"\",\"next\":2,\"dropped\":0,\"frames\":["
            "{\"seq\":0,\"time_us\":1700000000123456,\"dir\":\"to_servos\",\"kind\":\"request\",\"servo\":1,"
            "\"servos\":[1],\"instruction\":\"WRITE\",\"code\":3,\"fields\":["
            "{\"name\":\"goal_position\",\"address\":42,\"value\":2048},"
            "{\"name\":\"goal_time\",\"address\":44,\"value\":0},"
            "{\"name\":\"goal_speed\",\"address\":46,\"value\":1000}],"
            "\"status\":null,\"status_bits\":[],\"error\":\"\",\"retry\":false,"
            "\"bytes\":\"FF FF 01 09 03 2A 00 08 00 00 E8 03 D5\"},"
            "{\"seq\":1,\"time_us\":1700000000124000,\"dir\":\"from_servos\",\"kind\":\"answer\",\"servo\":1,"
            "\"servos\":[1],\"instruction\":\"WRITE\",\"code\":null,\"fields\":[],\"status\":32,"
            "\"status_bits\":[\"overload\"],\"error\":\"\",\"retry\":false,\"bytes\":\"FF FF 01 02 20 DC\"}]}");
}

}  // namespace
}  // namespace sms::gateway
