// Sparkplug B topics and payloads. The encoding is checked against protoc's own decoder (an
// independent reading of the same .proto), so a field number or wire type of ours that drifted
// from the specification's shows here and not first at a SCADA host.
#include "protocol/sparkplug/sparkplug.h"

#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <fstream>
#include <string>

namespace sms::sparkplug {
namespace {

TEST(SparkplugTopic, NodeAndDeviceTopicsRoundTrip) {
  const Topic node{"plant-a", MessageType::NBirth, "gw1", ""};
  EXPECT_EQ(topic_text(node), "spBv1.0/plant-a/NBIRTH/gw1");
  EXPECT_EQ(parse_topic(topic_text(node)), node);
  const Topic device{"plant-a", MessageType::DCmd, "gw1", "arm-3"};
  EXPECT_EQ(topic_text(device), "spBv1.0/plant-a/DCMD/gw1/arm-3");
  EXPECT_EQ(parse_topic(topic_text(device)), device);
}

TEST(SparkplugTopic, RefusesWhatIsNotANodeOrDeviceTopic) {
  EXPECT_FALSE(parse_topic("spBv1.0/g/DCMD/gw1"));      // device type without a device
  EXPECT_FALSE(parse_topic("spBv1.0/g/NCMD/gw1/dev"));  // node type with a device
  EXPECT_FALSE(parse_topic("spBv1.0/STATE/host"));      // a host's state topic
  EXPECT_FALSE(parse_topic("spAv1.0/g/NCMD/gw1"));      // another namespace
  EXPECT_FALSE(parse_topic("spBv1.0/g/NOPE/gw1"));
  EXPECT_FALSE(parse_topic("spBv1.0//NCMD/gw1"));  // empty group
  EXPECT_FALSE(parse_topic("spBv1.0/g/DCMD/gw1/a/b"));
  EXPECT_TRUE(valid_id("line_3.cell-2"));
  EXPECT_FALSE(valid_id("a/b"));
  EXPECT_FALSE(valid_id("a+"));
  EXPECT_FALSE(valid_id("#"));
  EXPECT_FALSE(valid_id(""));
}

TEST(SparkplugPayload, EveryValueKindRoundTrips) {
  Payload payload;
  payload.timestamp = 1'700'000'000'123;
  payload.seq = 255;
  payload.metrics.push_back(Metric::int16("present_load", -1000));
  payload.metrics.push_back(Metric::uint16("present_position", 65535));
  payload.metrics.push_back(Metric::uint32("replies_ok", 4'000'000'000u));
  payload.metrics.push_back(Metric::int64(std::string(kBdSeqMetric), 7));
  payload.metrics.push_back(Metric::uint64("timeouts", 4'000'000'000u));
  payload.metrics.push_back(Metric::int64("offset", -5'000'000'000));
  payload.metrics.push_back(Metric::boolean(std::string(kRebirthMetric), false));
  payload.metrics.push_back(Metric::string("last_command", "ok"));
  auto with_unit = Metric::uint16("present_voltage", 121);
  with_unit.eng_unit = "0.1 V";
  with_unit.read_only = true;
  with_unit.timestamp = 1'700'000'000'000;
  payload.metrics.push_back(with_unit);
  auto null_metric = Metric::uint16("goal_position", 0);
  null_metric.value = std::monostate{};
  payload.metrics.push_back(null_metric);

  const auto decoded = decode(encode(payload));
  ASSERT_TRUE(decoded) << decoded.error();
  EXPECT_EQ(*decoded, payload);
}

TEST(SparkplugPayload, NarrowSignedValuesAreSignExtendedEitherWay) {
  // An Int16 of -2 as our encoder writes it (32-bit two's complement) and as a host that
  // writes only the 16 low bits would.
  Payload payload;
  payload.metrics.push_back(Metric::int16("a", -2));
  auto decoded = decode(encode(payload));
  ASSERT_TRUE(decoded);
  EXPECT_EQ(std::get<std::int64_t>(decoded->metrics[0].value), -2);

  payload.metrics[0].value = std::int64_t{0xFFFE};  // the low 16 bits only
  decoded = decode(encode(payload));
  ASSERT_TRUE(decoded);
  EXPECT_EQ(std::get<std::int64_t>(decoded->metrics[0].value), -2);
}

TEST(SparkplugPayload, GarbageAndNamelessMetricsAreRefusedWithAReason) {
  const std::array<std::uint8_t, 3> garbage{0xFF, 0xFF, 0xFF};
  const auto bad = decode(garbage);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().find("not a Sparkplug B payload"), std::string::npos) << bad.error();

  Payload nameless;
  nameless.metrics.push_back(Metric::uint16("", 1));
  const auto refused = decode(encode(nameless));
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().find("without a name"), std::string::npos) << refused.error();

  Payload too_wide;
  too_wide.metrics.push_back(Metric::uint32("x", 70000));
  too_wide.metrics[0].type = DataType::UInt16;  // declared 16 bits, carries 17
  const auto wide = decode(encode(too_wide));
  ASSERT_FALSE(wide);
  EXPECT_NE(wide.error().find("does not fit UInt16"), std::string::npos) << wide.error();
}

TEST(SparkplugPayload, IntegerValueTakesWholeNumbersOnly) {
  EXPECT_EQ(integer_value(MetricValue{std::int64_t{-5}}), -5);
  EXPECT_EQ(integer_value(MetricValue{std::uint64_t{7}}), 7);
  EXPECT_EQ(integer_value(MetricValue{true}), 1);
  EXPECT_EQ(integer_value(MetricValue{2048.0}), 2048);
  EXPECT_EQ(integer_value(MetricValue{2048.0f}), 2048);
  EXPECT_FALSE(integer_value(MetricValue{2048.5}));
  EXPECT_FALSE(integer_value(MetricValue{std::string("2048")}));
  EXPECT_FALSE(integer_value(MetricValue{}));
  EXPECT_FALSE(integer_value(MetricValue{std::numeric_limits<std::uint64_t>::max()}));
}

TEST(SparkplugPayload, CommandMetricsWithoutADatatypeAreReadAsTheirBirthSays) {
  // A host following the spec sends no datatype in a DCMD: goal_position -100 (an Int16 in
  // DBIRTH) as int_value 0xFFFFFF9C, bytes written here by hand (payload.metrics = 2, name = 1,
  // int_value = 10).
  std::vector<std::uint8_t> bytes{0x12, 0x15, 0x0A, 0x0D};
  for (const char c : std::string("goal_position")) bytes.push_back(static_cast<std::uint8_t>(c));
  for (const std::uint8_t b : {0x50, 0x9C, 0xFF, 0xFF, 0xFF, 0x0F}) bytes.push_back(b);
  const auto as_born = decode(
      bytes, [](std::string_view name) { return name == "goal_position" ? DataType::Int16 : DataType::Unknown; });
  ASSERT_TRUE(as_born) << as_born.error();
  EXPECT_EQ(as_born->metrics[0].type, DataType::Int16);
  EXPECT_EQ(as_born->metrics[0].value, MetricValue{std::int64_t{-100}});
  // Without the birth's types: Unknown, and the 32 bits as they are.
  const auto raw = decode(bytes);
  ASSERT_TRUE(raw) << raw.error();
  EXPECT_EQ(raw->metrics[0].type, DataType::Unknown);
  EXPECT_EQ(raw->metrics[0].value, MetricValue{std::uint64_t{0xFFFFFF9C}});
  // The 16-bit spelling of a negative Int16 (0xFF9C) is accepted only from a sender that declared
  // Int16; from the birth's type nothing says the sender meant -100 and not 65436: refused.
  bytes = {0x12, 0x13, 0x0A, 0x0D};
  for (const char c : std::string("goal_position")) bytes.push_back(static_cast<std::uint8_t>(c));
  for (const std::uint8_t b : {0x50, 0x9C, 0xFF, 0x03}) bytes.push_back(b);
  const auto low_bits = decode(bytes, [](std::string_view) { return DataType::Int16; });
  ASSERT_FALSE(low_bits);
  EXPECT_EQ(low_bits.error(), "metric 'goal_position': 65436 does not fit Int16");
  // A declared datatype wins over the birth's.
  Payload declared;
  declared.metrics.push_back(Metric::uint16("goal_position", 40000));
  const auto kept = decode(encode(declared), [](std::string_view) { return DataType::Int16; });
  ASSERT_TRUE(kept);
  EXPECT_EQ(kept->metrics[0].type, DataType::UInt16);
  EXPECT_EQ(kept->metrics[0].value, MetricValue{std::uint64_t{40000}});
}

TEST(SparkplugPayload, IntegerRangesOfTheIntegerTypes) {
  EXPECT_EQ(integer_range(DataType::Int16)->min, -32768);
  EXPECT_EQ(integer_range(DataType::Int16)->max, 32767);
  EXPECT_EQ(integer_range(DataType::UInt16)->max, 65535);
  EXPECT_EQ(integer_range(DataType::UInt8)->max, 255);
  EXPECT_EQ(integer_range(DataType::UInt32)->max, 4294967295);
  EXPECT_FALSE(integer_range(DataType::Boolean));
  EXPECT_FALSE(integer_range(DataType::Float));
  EXPECT_FALSE(integer_range(DataType::String));
  EXPECT_FALSE(integer_range(DataType::Unknown));
}

std::optional<HostState> host_state(std::string_view json) {
  const auto state = parse_host_state(json);
  if (!state) return std::nullopt;
  return *state;
}

TEST(SparkplugState, HostStatePayloadsAndTopic) {
  EXPECT_EQ(state_topic("scada-1"), "spBv1.0/STATE/scada-1");
  EXPECT_EQ(host_state(R"({"online" : true, "timestamp" : 1668114759262})"), (HostState{true, 1668114759262}));
  EXPECT_EQ(host_state(R"({"timestamp":5,"online":false})"), (HostState{false, 5}));
  // Keys of later versions are skipped, nested or not.
  EXPECT_EQ(host_state(R"( {"online":true,"x":{"a":[1,"}",null]},"timestamp":7,"y":"z"} )"), (HostState{true, 7}));
  EXPECT_EQ(host_state(host_state_json(HostState{false, 42})), (HostState{false, 42}));

  const auto error = [](std::string_view json) {
    const auto state = parse_host_state(json);
    return state ? std::string("accepted") : state.error();
  };
  EXPECT_EQ(error("ONLINE"),
            R"(not a Sparkplug 3.0 STATE payload (expected JSON {"online": true|false, "timestamp": <ms>}))");
  EXPECT_EQ(error(R"({"timestamp":5})"), "STATE: no `online` key");
  EXPECT_EQ(error(R"({"online":"yes","timestamp":5})"), "STATE: `online` is not true or false");
  EXPECT_EQ(error(R"({"online":true})"), "STATE: no `timestamp` key");
  EXPECT_EQ(error(R"({"online":true,"timestamp":-1})"),
            "STATE: `timestamp` is not a whole number of ms since the epoch");
  EXPECT_EQ(error(R"({"online":true,"timestamp":1.5})"),
            "STATE: `timestamp` is not a whole number of ms since the epoch");
  EXPECT_NE(error(R"({"online":true,"timestamp":5} x)"), "accepted");
  EXPECT_NE(error(R"({"online":true,"timestamp":5)"), "accepted");
  EXPECT_NE(error(""), "accepted");
}

std::string run(const std::string& command) {
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return "<popen failed>";
  std::string text;
  std::array<char, 256> buffer{};
  while (fgets(buffer.data(), buffer.size(), pipe)) text += buffer.data();
  if (pclose(pipe) != 0) text += "<exit status not 0>";
  return text;
}

// protoc --decode_raw knows no schema: it shows our bytes as field numbers and wire values, which
// are checked here against the numbers of the specification's Payload table (timestamp 1,
// metrics 2, seq 3; metric name 1, timestamp 3, datatype 4, int_value 10, long_value 11).
TEST(SparkplugPayload, ProtocDecodeRawShowsTheSpecificationsFieldNumbers) {
  Payload payload;
  payload.timestamp = 1234;
  payload.seq = 3;
  auto position = Metric::int16("present_load", -3);
  position.timestamp = 99;
  payload.metrics.push_back(position);
  payload.metrics.push_back(Metric::int64(std::string(kBdSeqMetric), 5));
  const auto bytes = encode(payload);
  const std::string in = ::testing::TempDir() + "sparkplug_raw.bin";
  std::ofstream(in, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  const std::string text = run(std::string(SMS_PROTOC) + " --decode_raw < " + in);
  EXPECT_NE(text.find("1: 1234\n"), std::string::npos) << text;
  EXPECT_NE(text.find("3: 3\n"), std::string::npos) << text;
  EXPECT_NE(text.find("2 {\n  1: \"present_load\"\n  3: 99\n  4: 2\n  10: 4294967293\n}"), std::string::npos) << text;
  EXPECT_NE(text.find("2 {\n  1: \"bdSeq\"\n  4: 4\n  11: 5\n}"), std::string::npos) << text;
}

// protoc --decode reads our bytes with the .proto: names, numbers and types as protoc sees them.
TEST(SparkplugPayload, ProtocDecodesOurBytesAsTheSpecificationsFields) {
  Payload payload;
  payload.timestamp = 1234;
  payload.seq = 3;
  payload.metrics.push_back(Metric::int16("present_load", -3));
  payload.metrics.push_back(Metric::boolean("torque_enable", true));
  const auto bytes = encode(payload);
  const std::string in = ::testing::TempDir() + "sparkplug_payload.bin";
  std::ofstream(in, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  const std::string command = std::string(SMS_PROTOC) + " --proto_path=" + SMS_SPARKPLUG_PROTO_DIR +
                              " --decode=sms.sparkplug.wire.Payload sparkplug_b.proto < " + in;
  FILE* pipe = popen(command.c_str(), "r");
  ASSERT_NE(pipe, nullptr);
  std::string text;
  std::array<char, 256> buffer{};
  while (fgets(buffer.data(), buffer.size(), pipe)) text += buffer.data();
  ASSERT_EQ(pclose(pipe), 0) << text;
  EXPECT_NE(text.find("timestamp: 1234"), std::string::npos) << text;
  EXPECT_NE(text.find("seq: 3"), std::string::npos) << text;
  EXPECT_NE(text.find("name: \"present_load\""), std::string::npos) << text;
  EXPECT_NE(text.find("datatype: 2"), std::string::npos) << text;            // Int16
  EXPECT_NE(text.find("int_value: 4294967293"), std::string::npos) << text;  // -3 in 32 bits
  EXPECT_NE(text.find("datatype: 11"), std::string::npos) << text;           // Boolean
  EXPECT_NE(text.find("boolean_value: true"), std::string::npos) << text;
}

}  // namespace
}  // namespace sms::sparkplug
