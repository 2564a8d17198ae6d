// Builders against hand-computed frames, and encode -> decode -> parse round trips for every
// instruction of both packet protocols (docs/PROTOCOL.md §1.1, §1.2).
#include <gtest/gtest.h>

#include <algorithm>
#include <functional>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"
#include "protocol/stream_decoder.h"

namespace sms::protocol {
namespace {

// Encodes, decodes through a StreamDecoder and returns the one packet it must yield.
Packet through_the_wire(const PacketFormat& format, const Packet& packet) {
  StreamDecoder decoder(format);
  decoder.feed(encode(format, packet));
  auto event = decoder.next();
  EXPECT_TRUE(event.has_value());
  if (!event) return {};
  EXPECT_EQ(event->kind, DecodeEvent::Kind::Frame);
  EXPECT_FALSE(decoder.next().has_value());
  return event->packet;
}

// One round trip per instruction: the builder's frame, hand-computed, and a check that the
// decoded packet parses back into what was built.
struct RoundTrip {
  std::string name;
  Packet packet;
  Bytes frame;
  std::function<void(const Packet&)> check_parsed;
};

void run_round_trips(const PacketFormat& format, const std::vector<RoundTrip>& trips,
                     std::span<const InstructionSpec> instructions) {
  std::set<std::uint8_t> covered;
  for (const auto& trip : trips) {
    SCOPED_TRACE(trip.name);
    EXPECT_EQ(encode(format, trip.packet), trip.frame);
    const Packet decoded = through_the_wire(format, trip.packet);
    EXPECT_EQ(decoded, trip.packet);
    trip.check_parsed(decoded);
    covered.insert(trip.packet.code);
  }
  for (const auto& instruction : instructions) {
    EXPECT_TRUE(covered.count(instruction.code)) << instruction.name << " has no round trip";
  }
}

void no_params(const Packet& packet) { EXPECT_TRUE(packet.params.empty()); }

const std::vector<SyncWriteEntry> kFeetechSyncEntries{{1, {0x00, 0x08}}, {2, {0xFF, 0x07}}};
const std::vector<SyncWriteEntry> kD55dSyncEntries{{1, {0x10, 0x27}}, {2, {0xE8, 0x03}}};
const std::vector<std::uint8_t> kSyncReadIds{1, 2};
const std::vector<d55d::TrajectoryPoint> kTrajectory{{900, 50}, {1800, 100}};
const Bytes kWriteData{0x00, 0x08, 0x00, 0x00, 0xE8, 0x03};

TEST(FeetechInstructions, EveryInstructionRoundTrips) {
  const std::vector<RoundTrip> trips{
      {"PING", ping(1), {0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB}, no_params},
      {"READ",
       read(1, 56, 2),
       {0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE},
       [](const Packet& p) {
         auto request = parse_read(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 56);
         EXPECT_EQ(request->count, 2);
       }},
      {"WRITE",
       write(1, 42, kWriteData),
       {0xFF, 0xFF, 0x01, 0x09, 0x03, 0x2A, 0x00, 0x08, 0x00, 0x00, 0xE8, 0x03, 0xD5},
       [](const Packet& p) {
         auto request = parse_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 42);
         EXPECT_EQ(request->data, kWriteData);
       }},
      {"REG WRITE",
       reg_write(2, 42, Bytes{0x00, 0x08}),
       {0xFF, 0xFF, 0x02, 0x05, 0x04, 0x2A, 0x00, 0x08, 0xC2},
       [](const Packet& p) {
         auto request = parse_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 42);
         EXPECT_EQ(request->data, (Bytes{0x00, 0x08}));
       }},
      {"ACTION", action(), {0xFF, 0xFF, 0xFE, 0x02, 0x05, 0xFA}, no_params},
      {"RECOVERY", feetech::recovery(1), {0xFF, 0xFF, 0x01, 0x02, 0x06, 0xF6}, no_params},
      {"REBOOT", feetech::reboot(1), {0xFF, 0xFF, 0x01, 0x02, 0x08, 0xF4}, no_params},
      {"BACKUP", feetech::backup(1), {0xFF, 0xFF, 0x01, 0x02, 0x09, 0xF3}, no_params},
      {"RESET STATUS", feetech::reset_status(1), {0xFF, 0xFF, 0x01, 0x02, 0x0A, 0xF2}, no_params},
      {"CALIBRATE to 1024",
       feetech::calibrate(1, 1024),
       {0xFF, 0xFF, 0x01, 0x04, 0x0B, 0x00, 0x04, 0xEB},
       [](const Packet& p) {
         auto position = feetech::parse_calibrate(p.params);
         ASSERT_TRUE(position);
         EXPECT_EQ(*position, std::optional<std::uint16_t>(1024));
       }},
      {"CALIBRATE to 2048",
       feetech::calibrate(1),
       {0xFF, 0xFF, 0x01, 0x02, 0x0B, 0xF1},
       [](const Packet& p) {
         auto position = feetech::parse_calibrate(p.params);
         ASSERT_TRUE(position);
         EXPECT_EQ(*position, std::nullopt);
       }},
      {"SYNC READ",
       feetech::sync_read(56, 8, kSyncReadIds),
       {0xFF, 0xFF, 0xFE, 0x06, 0x82, 0x38, 0x08, 0x01, 0x02, 0x36},
       [](const Packet& p) {
         auto request = feetech::parse_sync_read(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 56);
         EXPECT_EQ(request->count, 8);
         EXPECT_EQ(request->ids, kSyncReadIds);
       }},
      {"SYNC WRITE",
       sync_write(42, 2, kFeetechSyncEntries),
       {0xFF, 0xFF, 0xFE, 0x0A, 0x83, 0x2A, 0x02, 0x01, 0x00, 0x08, 0x02, 0xFF, 0x07, 0x37},
       [](const Packet& p) {
         auto request = parse_sync_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 42);
         EXPECT_EQ(request->length, 2);
         EXPECT_EQ(request->entries, kFeetechSyncEntries);
       }},
  };
  run_round_trips(kFeetechFormat, trips, feetech::kInstructions);
}

TEST(D55dInstructions, EveryInstructionRoundTrips) {
  using namespace d55d;
  auto custom_parses_to = [](const CustomMove& expected) {
    return [expected](const Packet& p) {
      auto move = parse_custom(p.params);
      ASSERT_TRUE(move);
      EXPECT_EQ(*move, expected);
    };
  };
  const RelativeMove relative{3600, 0x812C, std::nullopt, std::nullopt};  // 300 clockwise (bit 15)
  const RelativeMove relative_ramped{3600, 0x812C, 10, 20};
  const AbsoluteMove absolute{1800, 500, 5, 6};
  const ChangeSpeed change{1000};
  const std::vector<RoundTrip> trips{
      {"PING", ping(1), {0xD5, 0x5D, 0x01, 0x02, 0x01, 0x04}, no_params},
      {"READ",
       read(1, 36, 2),
       {0xD5, 0x5D, 0x01, 0x04, 0x02, 0x24, 0x02, 0x2D},
       [](const Packet& p) {
         auto request = parse_read(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 36);
         EXPECT_EQ(request->count, 2);
       }},
      {"WRITE (docs/PROTOCOL.md example: every ID to 1)",
       write(kBroadcastId, 3, Bytes{0x01}),
       {0xD5, 0x5D, 0xFE, 0x04, 0x03, 0x03, 0x01, 0x09},
       [](const Packet& p) {
         auto request = parse_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 3);
         EXPECT_EQ(request->data, (Bytes{0x01}));
       }},
      {"REG WRITE",
       reg_write(1, 30, Bytes{0x10, 0x27}),
       {0xD5, 0x5D, 0x01, 0x05, 0x04, 0x1E, 0x10, 0x27, 0x5F},
       [](const Packet& p) {
         auto request = parse_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 30);
         EXPECT_EQ(request->data, (Bytes{0x10, 0x27}));
       }},
      {"ACTION", action(), {0xD5, 0x5D, 0xFE, 0x02, 0x05, 0x05}, no_params},
      {"RESET", reset(1), {0xD5, 0x5D, 0x01, 0x02, 0x06, 0x09}, no_params},
      {"START END",
       start_end(1, Bytes{0x01, 0x02}),
       {0xD5, 0x5D, 0x01, 0x04, 0x07, 0x01, 0x02, 0x0F},
       [](const Packet& p) {
         EXPECT_EQ(p.params, (Bytes{0x01, 0x02}));
       }},
      {"TRAJECTORY WRITE",
       trajectory_write(1, kTrajectory),
       {0xD5, 0x5D, 0x01, 0x09, 0x0A, 0x02, 0x84, 0x03, 0x32, 0x08, 0x07, 0x64, 0x42},
       [](const Packet& p) {
         auto points = parse_trajectory_write(p.params);
         ASSERT_TRUE(points);
         EXPECT_EQ(*points, kTrajectory);
       }},
      {"TRAJECTORY ACTION", trajectory_action(1), {0xD5, 0x5D, 0x01, 0x02, 0x0B, 0x0E}, no_params},
      {"SYNC WRITE",
       sync_write(30, 2, kD55dSyncEntries),
       {0xD5, 0x5D, 0xFE, 0x0A, 0x83, 0x1E, 0x02, 0x01, 0x10, 0x27, 0x02, 0xE8, 0x03, 0xD0},
       [](const Packet& p) {
         auto request = parse_sync_write(p.params);
         ASSERT_TRUE(request);
         EXPECT_EQ(request->address, 30);
         EXPECT_EQ(request->entries, kD55dSyncEntries);
       }},
      {"CUSTOM relative, 4 bytes",
       custom(1, relative),
       {0xD5, 0x5D, 0x01, 0x07, 0xFF, 0x01, 0x10, 0x0E, 0x2C, 0x81, 0xD3},
       custom_parses_to(relative)},
      {"CUSTOM relative, 6 bytes",
       custom(1, relative_ramped),
       {0xD5, 0x5D, 0x01, 0x09, 0xFF, 0x01, 0x10, 0x0E, 0x2C, 0x81, 0x0A, 0x14, 0xF3},
       custom_parses_to(relative_ramped)},
      {"CUSTOM absolute",
       custom(1, absolute),
       {0xD5, 0x5D, 0x01, 0x09, 0xFF, 0x02, 0x08, 0x07, 0xF4, 0x01, 0x05, 0x06, 0x1A},
       custom_parses_to(absolute)},
      {"CUSTOM change speed",
       custom(1, change),
       {0xD5, 0x5D, 0x01, 0x05, 0xFF, 0x03, 0xE8, 0x03, 0xF3},
       custom_parses_to(change)},
  };
  run_round_trips(kD55dFormat, trips, d55d::kInstructions);
}

TEST(Instructions, StatusReplyCarriesTheErrorByteAsCode) {
  EXPECT_EQ(encode(kFeetechFormat, status(1, 0x00, Bytes{0x18, 0x05})),
            (Bytes{0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD}));
  // d55d PING reply as the document prints it: ERROR byte 01, one parameter.
  EXPECT_EQ(encode(kD55dFormat, status(1, 0x01, Bytes{0x00})), (Bytes{0xD5, 0x5D, 0x01, 0x03, 0x01, 0x00, 0x05}));
}

TEST(Instructions, ParsersRejectMalformedParameters) {
  EXPECT_FALSE(parse_read(Bytes{}));
  EXPECT_FALSE(parse_read(Bytes{56}));
  EXPECT_FALSE(parse_read(Bytes{56, 0}));  // a READ of nothing
  EXPECT_FALSE(parse_read(Bytes{56, 2, 0}));
  EXPECT_FALSE(parse_write(Bytes{}));
  EXPECT_FALSE(parse_write(Bytes{42}));  // address, no data
  EXPECT_FALSE(parse_sync_write(Bytes{42}));
  EXPECT_FALSE(parse_sync_write(Bytes{42, 2}));                    // no servo
  EXPECT_FALSE(parse_sync_write(Bytes{42, 0, 1}));                 // zero-length data
  EXPECT_FALSE(parse_sync_write(Bytes{42, 2, 1, 0x00, 0x08, 2}));  // second entry cut short
  EXPECT_FALSE(parse_sync_write(Bytes{42, 2, 1, 0x00}));
}

TEST(FeetechInstructions, ParsersRejectMalformedParameters) {
  EXPECT_FALSE(feetech::parse_sync_read(Bytes{56, 8}));  // no id
  EXPECT_FALSE(feetech::parse_sync_read(Bytes{56, 0, 1}));
  EXPECT_FALSE(feetech::parse_calibrate(Bytes{0x00}));
  EXPECT_FALSE(feetech::parse_calibrate(Bytes{0x00, 0x04, 0x00}));
}

TEST(D55dInstructions, ParsersRejectMalformedParameters) {
  using namespace d55d;
  EXPECT_FALSE(parse_trajectory_write(Bytes{}));
  EXPECT_FALSE(parse_trajectory_write(Bytes{0}));
  EXPECT_FALSE(parse_trajectory_write(Bytes{2, 0x84, 0x03, 0x32}));  // count says 2, one point
  EXPECT_FALSE(parse_trajectory_write(Bytes{1, 0x84, 0x03, 0x32, 0x00}));
  EXPECT_FALSE(parse_custom(Bytes{}));
  EXPECT_FALSE(parse_custom(Bytes{0x01, 0x10, 0x0E, 0x2C}));              // relative, 3 bytes
  EXPECT_FALSE(parse_custom(Bytes{0x01, 0x10, 0x0E, 0x2C, 0x81, 0x0A}));  // relative, 5 bytes
  EXPECT_FALSE(parse_custom(Bytes{0x02, 0x08, 0x07, 0xF4, 0x01}));        // absolute, 4 bytes
  EXPECT_FALSE(parse_custom(Bytes{0x03, 0xE8}));
  EXPECT_FALSE(parse_custom(Bytes{0x04, 0xE8, 0x03}));  // unknown sub-command
}

TEST(Instructions, BuildersRefuseWhatCannotBeFramed) {
  const std::vector<SyncWriteEntry> ragged{{1, {0x00, 0x08}}, {2, {0xFF}}};
  EXPECT_THROW(sync_write(42, 2, ragged), std::invalid_argument);
  EXPECT_THROW(sync_write(42, 2, std::vector<SyncWriteEntry>{}), std::invalid_argument);
  // (2+1) x 84 + 2 = 254 parameter bytes: one more than LEN allows.
  std::vector<SyncWriteEntry> too_many(84, SyncWriteEntry{1, {0x00, 0x00}});
  EXPECT_THROW(sync_write(42, 2, too_many), std::length_error);
  too_many.pop_back();
  EXPECT_EQ(sync_write(42, 2, too_many).params.size(), 251U);

  EXPECT_THROW(feetech::sync_read(56, 8, std::vector<std::uint8_t>{}), std::invalid_argument);
  EXPECT_THROW(feetech::sync_read(56, 8, std::vector<std::uint8_t>(252, 1)), std::length_error);
  EXPECT_EQ(feetech::sync_read(56, 8, std::vector<std::uint8_t>(251, 1)).params.size(), 253U);

  EXPECT_THROW(d55d::trajectory_write(1, std::vector<d55d::TrajectoryPoint>{}), std::invalid_argument);
  EXPECT_THROW(d55d::trajectory_write(1, std::vector<d55d::TrajectoryPoint>(85)), std::length_error);
  EXPECT_EQ(d55d::trajectory_write(1, std::vector<d55d::TrajectoryPoint>(84)).params.size(), 253U);
  EXPECT_THROW(d55d::custom(1, d55d::RelativeMove{1, 1, 10, std::nullopt}), std::invalid_argument);
}

TEST(Instructions, NamesComeFromEachProtocolsTable) {
  EXPECT_EQ(feetech::instruction_name(0x82), std::optional<std::string_view>("SYNC READ"));
  EXPECT_EQ(feetech::instruction_name(0xFF), std::nullopt);
  EXPECT_EQ(d55d::instruction_name(0xFF), std::optional<std::string_view>("CUSTOM"));
  EXPECT_EQ(d55d::instruction_name(0x82), std::nullopt);  // d55d has no SYNC READ
  EXPECT_EQ(d55d::instruction_name(0x06), std::optional<std::string_view>("RESET"));
  EXPECT_EQ(feetech::instruction_name(0x06), std::optional<std::string_view>("RECOVERY"));
}

}  // namespace
}  // namespace sms::protocol
