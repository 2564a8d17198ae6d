// MQTT Sparkplug B end to end (docs/MQTT.md): a real Mosquitto broker on loopback,
// the real sms-gateway and sms-sim, and a Sparkplug host stand-in (libmosquitto). Births and
// deaths follow the servos, data follows the poll cache, commands move the simulated servo through
// the same rules as Modbus writes after a check of their type and range, the broker going away
// loses nothing, the bdSeq survives a restart, a primary host's STATE gates the births, and protoc
// reads what a host gets.
#include <gtest/gtest.h>

#include <signal.h>

#include "tests/e2e/mqtt_support.h"
#include "tests/support/eventually.h"
#include "tests/support/modbus_client.h"

// Its own namespace: the test files of e2e_tests compile in batches (unity build), where the
// helpers of one file's anonymous namespace would meet another's of the same name.
namespace sms::e2e::sparkplug_test {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

namespace sp = sparkplug;
using sp::MessageType;

constexpr const char* kGroup = "plant";
constexpr const char* kNode = "gw1";

std::string gateway_yaml(const std::string& pty, std::uint16_t broker, const std::string& mqtt_extra = "") {
  return "buses:\n"
         "  - {name: arm, device: \"" +
         pty +
         "\", protocol: feetech, baud: 1000000, poll_period_ms: 20,\n"
         "     response_timeout_ms: 200, offline_probe_period_ms: 50}\n"
         "servos:\n"
         "  - {unit: 1, bus: arm, id: 1, table: sts, name: shoulder}\n"
         "  - {unit: 2, bus: arm, id: 2, table: sts}\n"
         "mqtt:\n"
         "  broker: \"127.0.0.1:" +
         std::to_string(broker) +
         "\"\n"
         "  group_id: plant\n"
         "  edge_node_id: gw1\n"
         "  data_period_ms: 20\n"
         "  reconnect_min_ms: 100\n"
         "  reconnect_max_ms: 400\n" +
         mqtt_extra;
}

std::optional<std::int64_t> int_of(const sp::Metric* metric) {
  if (metric == nullptr) return std::nullopt;
  return sp::integer_value(metric->value);
}

std::string text_of(const sp::Metric* metric) {
  if (metric == nullptr) return "<no metric>";
  if (const auto* s = std::get_if<std::string>(&metric->value)) return *s;
  return "<not a string>";
}

// Sends one DCMD to device `shoulder` and returns its Gateway/Last Command as the next DDATA
// carrying one reports it ("<none>" when none came within 10 s).
std::string command_result(SparkplugHost& host, sp::Metric metric) {
  const std::size_t from = host.count();
  host.command(MessageType::DCmd, kGroup, kNode, "shoulder", {std::move(metric)});
  const auto answer = host.wait(
      [](const SparkplugMessage& m) {
        return m.topic.type == MessageType::DData && m.metric("Gateway/Last Command") != nullptr;
      },
      10s, from);
  return answer ? text_of(answer->metric("Gateway/Last Command")) : "<none>\n" + host.summary();
}

struct Plant {
  TempDir dir;
  MosquittoBroker broker{dir};
  SimProcess sim{dir, "sim", {"--ids", "1-2"}};
  SparkplugHost host{broker.port()};
};

TEST(Sparkplug, BirthsCarryEveryFieldAndDeathsFollowTheServo) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);

  const auto nbirth = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(nbirth) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(nbirth->topic.group, kGroup);
  EXPECT_EQ(nbirth->topic.edge_node, kNode);
  EXPECT_EQ(nbirth->payload.seq, 0u);
  ASSERT_TRUE(int_of(nbirth->metric("bdSeq")));
  ASSERT_NE(nbirth->metric("Node Control/Rebirth"), nullptr);
  EXPECT_EQ(int_of(nbirth->metric("Gateway/E-Stop")), 0);
  // The heartbeat as holding 1000 of the gateway unit reads it: 0 before any write, not null.
  ModbusClient panel(gateway.port(), 255);
  const auto heartbeat = panel.read_holding(1000, 1);
  ASSERT_TRUE(heartbeat.ok()) << heartbeat.error;
  EXPECT_EQ(int_of(nbirth->metric("Gateway/Heartbeat/arm")), heartbeat.values.at(0));

  for (const std::string device : {"shoulder", "unit-2"}) {
    const auto dbirth = plant.host.wait(is(MessageType::DBirth, device));
    ASSERT_TRUE(dbirth) << device << "\n" << plant.host.summary();
    const auto* position = dbirth->metric("present_position");
    ASSERT_NE(position, nullptr);
    EXPECT_EQ(position->type, sp::DataType::Int16);  // sts positions are signed
    EXPECT_TRUE(position->read_only);
    EXPECT_EQ(position->eng_unit, "steps");
    const int id = device == "shoulder" ? 1 : 2;
    EXPECT_EQ(int_of(position), plant.sim.field(id, "present_position"));
    const auto* goal = dbirth->metric("goal_position");
    ASSERT_NE(goal, nullptr);
    EXPECT_FALSE(goal->read_only);
    EXPECT_EQ(int_of(goal), plant.sim.field(id, "goal_position"));
    EXPECT_NE(dbirth->metric("Gateway/Status"), nullptr);
    EXPECT_NE(dbirth->metric("Gateway/Last Command"), nullptr);
  }

  // The servo stops answering: DDEATH; it answers again: a new DBIRTH.
  const std::size_t before = plant.host.count();
  plant.sim.control("offline 2");
  ASSERT_TRUE(plant.host.wait(is(MessageType::DDeath, "unit-2"), 10s, before)) << plant.host.summary();
  const std::size_t dead = plant.host.count();
  plant.sim.control("online 2");
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "unit-2"), 10s, dead)) << plant.host.summary();
  EXPECT_FALSE(plant.host.wait(is(MessageType::DDeath, "shoulder"), 100ms));

  // Every message after NBIRTH carries the next seq (0..255).
  std::uint64_t expected = 0;
  bool in_order = true;
  plant.host.wait(
      [&](const SparkplugMessage& m) {
        if (m.topic.type == MessageType::NBirth) expected = 0;
        in_order = in_order && m.payload.seq == expected;
        expected = (expected + 1) % 256;
        return false;
      },
      0ms);
  EXPECT_TRUE(in_order) << plant.host.summary();
}

TEST(Sparkplug, DcmdMovesTheServoAndDdataFollows) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"))) << plant.host.summary();

  std::size_t from = plant.host.count();
  plant.host.command(MessageType::DCmd, kGroup, kNode, "shoulder",
                     {sp::Metric::uint16("torque_enable", 1), sp::Metric::int16("goal_position", 3000)});
  // The acknowledgement: the written value and the command's result in DDATA.
  const auto ack = plant.host.wait(
      [](const SparkplugMessage& m) {
        return m.topic.type == MessageType::DData && m.topic.device == "shoulder" &&
               m.metric("goal_position") != nullptr;
      },
      10s, from);
  ASSERT_TRUE(ack) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(ack->metric("goal_position")), 3000);
  EXPECT_EQ(text_of(ack->metric("Gateway/Last Command")), "ok: goal_position := 3000");
  EXPECT_EQ(plant.sim.field(1, "goal_position"), 3000);
  EXPECT_EQ(plant.sim.field(1, "torque_enable"), 1);

  // The simulated servo moves; DDATA reports its position from the poll cache until it is there.
  const auto arrived = plant.host.wait(
      [](const SparkplugMessage& m) {
        const auto* position = m.metric("present_position");
        return m.topic.type == MessageType::DData && m.topic.device == "shoulder" && position != nullptr &&
               std::llabs(sp::integer_value(position->value).value_or(0) - 3000) <= 2;
      },
      20s, from);
  ASSERT_TRUE(arrived) << plant.host.summary();
  ASSERT_TRUE(arrived->metric("present_position")->timestamp);  // when the poll read it

  // Refusals: a read-only field, an EEPROM field for role operate, a value out of range. The
  // servo keeps its value each time; Gateway/Last Command says why.
  const auto refused = [&](sp::Metric metric, const std::string& expected) {
    const std::string result = command_result(plant.host, metric);
    EXPECT_NE(result.find(expected), std::string::npos) << metric.name << ": " << result;
  };
  const long max_temperature = plant.sim.field(1, "max_temperature");
  refused(sp::Metric::int16("present_position", 5),
          "refused: present_position: exception 0x02 (illegal data address): present_position (56) of table sts "
          "is read-only");
  refused(sp::Metric::uint16("max_temperature", 60), "exception 0x02");
  refused(sp::Metric::uint16("torque_enable", 5), "exception 0x03");  // 0, 1 or 128
  refused(sp::Metric::string("goal_position", "fast"), "got String \"fast\", the metric is Int16");
  EXPECT_EQ(plant.sim.field(1, "goal_position"), 3000);
  EXPECT_EQ(plant.sim.field(1, "max_temperature"), max_temperature);
  EXPECT_EQ(plant.sim.field(1, "torque_enable"), 1);
}

TEST(Sparkplug, EstopOverNcmdBlocksMotionCommands) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"))) << plant.host.summary();
  const long goal = plant.sim.field(1, "goal_position");

  std::size_t from = plant.host.count();
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::boolean("Gateway/E-Stop", true)});
  const auto latched = plant.host.wait(
      [](const SparkplugMessage& m) {
        return m.topic.type == MessageType::NData && m.metric("Gateway/E-Stop") != nullptr;
      },
      10s, from);
  ASSERT_TRUE(latched) << plant.host.summary();
  EXPECT_EQ(int_of(latched->metric("Gateway/E-Stop")), 1);
  EXPECT_TRUE(gateway.process().wait_for_line("E-STOP latched by the Sparkplug host (NCMD/DCMD)", 2s))
      << gateway.process().output();

  const std::string result = command_result(plant.host, sp::Metric::int16("goal_position", 1000));
  // The write, the exception, and the rule that refused it in the words the console uses
  // (UnitRouter::refusal_reason): each once (docs/MQTT.md "Commands").
  EXPECT_EQ(result.rfind("refused: goal_position := 1000: exception 0x04", 0), 0u) << result;
  EXPECT_NE(result.find(": bus arm: the e-stop is latched; motion writes are refused until it is reset"),
            std::string::npos)
      << result;
  EXPECT_EQ(result.find("refused:", 1), std::string::npos) << "said once: " << result;
  EXPECT_EQ(result.find("goal_position", result.find("goal_position") + 1), std::string::npos)
      << "named once: " << result;
  EXPECT_EQ(plant.sim.field(1, "goal_position"), goal);

  // Garbage on the command topic and an unknown device: logged, counted, nothing written.
  plant.host.raw("spBv1.0/plant/DCMD/gw1/shoulder", {0xFF, 0xFF, 0xFF});
  plant.host.command(MessageType::DCmd, kGroup, kNode, "elbow", {sp::Metric::int16("goal_position", 1000)});
  EXPECT_TRUE(gateway.process().wait_for_line("not a Sparkplug B payload", 5s)) << gateway.process().output();
  EXPECT_TRUE(gateway.process().wait_for_line("no device `elbow`", 5s)) << gateway.process().output();
  EXPECT_EQ(plant.sim.field(1, "goal_position"), goal);
}

TEST(Sparkplug, RebirthAndHeartbeatOverNcmd) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(
      plant.dir,
      substitute(
          gateway_yaml(plant.sim.pty(), plant.broker.port()), "offline_probe_period_ms: 50}",
          "offline_probe_period_ms: 50, retries: 1,\n     watchdog: {timeout_ms: 1000, feed: heartbeat_register}}"),
      1);
  const auto first = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(first) << plant.host.summary() << gateway.process().output();
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "unit-2")));

  // Rebirth: NBIRTH again (same bdSeq: same session, seq from 0), then every DBIRTH.
  std::size_t from = plant.host.count();
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::boolean("Node Control/Rebirth", true)});
  const auto again = plant.host.wait(is(MessageType::NBirth), 10s, from);
  ASSERT_TRUE(again) << plant.host.summary();
  EXPECT_EQ(again->payload.seq, 0u);
  EXPECT_EQ(int_of(again->metric("bdSeq")), int_of(first->metric("bdSeq")));
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"), 10s, from));
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "unit-2"), 10s, from));

  // The heartbeat register through NCMD feeds the watchdog: a changing value every 100 ms keeps it
  // from tripping for well over its 1000 ms timeout, and motion commands pass meanwhile.
  static constexpr int kLastBeat = 20;
  for (int beat = 1; beat <= kLastBeat; ++beat) {
    plant.host.command(MessageType::NCmd, kGroup, kNode, "",
                       {sp::Metric::uint16("Gateway/Heartbeat/arm", static_cast<std::uint16_t>(beat))});
    std::this_thread::sleep_for(100ms);
  }
  EXPECT_FALSE(plant.host.wait(
      [](const SparkplugMessage& m) {
        const auto* tripped = m.metric("Gateway/Watchdog Tripped");
        return m.topic.type == MessageType::NData && tripped != nullptr && sp::integer_value(tripped->value) == 1;
      },
      0ms, from))
      << gateway.process().output();
  // The last beat, as NDATA reports it and as FC03 reads holding 1000: the same value.
  const auto beat_reported = plant.host.wait(
      [](const SparkplugMessage& m) {
        const auto* beat = m.metric("Gateway/Heartbeat/arm");
        return m.topic.type == MessageType::NData && beat != nullptr && sp::integer_value(beat->value) == kLastBeat;
      },
      10s, from);
  EXPECT_TRUE(beat_reported) << plant.host.summary();
  ModbusClient panel(gateway.port(), 255);
  const auto heartbeat = panel.read_holding(1000, 1);
  ASSERT_TRUE(heartbeat.ok()) << heartbeat.error;
  EXPECT_EQ(heartbeat.values.at(0), kLastBeat);
  // Heartbeats stop: the watchdog trips, NDATA says so, and re-arming over NCMD clears it.
  const auto tripped = plant.host.wait(
      [](const SparkplugMessage& m) {
        const auto* metric = m.metric("Gateway/Watchdog Tripped");
        return m.topic.type == MessageType::NData && metric != nullptr && sp::integer_value(metric->value) == 1;
      },
      10s, from);
  ASSERT_TRUE(tripped) << plant.host.summary() << gateway.process().output();
  from = plant.host.count();
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::boolean("Gateway/Watchdog Tripped", false)});
  ASSERT_TRUE(plant.host.wait(
      [](const SparkplugMessage& m) {
        const auto* metric = m.metric("Gateway/Watchdog Tripped");
        return m.topic.type == MessageType::NData && metric != nullptr && sp::integer_value(metric->value) == 0;
      },
      10s, from))
      << plant.host.summary() << gateway.process().output();
}

TEST(Sparkplug, RoleReadPublishesButRefusesEveryCommand) {
  Plant plant;
  auto gateway =
      GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port(), "  role: read\n"), 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder")))
      << plant.host.summary() << gateway.process().output();
  const long goal = plant.sim.field(1, "goal_position");
  const std::string result = command_result(plant.host, sp::Metric::int16("goal_position", 1234));
  EXPECT_NE(result.find("exception 0x01"), std::string::npos) << result;
  EXPECT_NE(result.find("role read"), std::string::npos) << result;
  EXPECT_EQ(plant.sim.field(1, "goal_position"), goal);
}

TEST(Sparkplug, AStoppingGatewaySendsItsOwnNdeath) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  const auto birth = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(birth) << plant.host.summary();
  gateway.process().signal(SIGTERM);
  ASSERT_EQ(gateway.process().wait_exit(10s), std::optional<int>{0}) << gateway.process().output();
  // Sent by the gateway before its DISCONNECT (a clean disconnect makes the broker drop the will).
  const auto death = plant.host.wait(is(MessageType::NDeath), 5s);
  ASSERT_TRUE(death) << plant.host.summary();
  EXPECT_EQ(int_of(death->metric("bdSeq")), int_of(birth->metric("bdSeq")));
  EXPECT_FALSE(death->payload.seq);  // NDEATH carries no seq (spec)
}

TEST(Sparkplug, BrokerDownAndBackGivesNewBirthsAndAKilledGatewayItsDeath) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  const auto first = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(first) << plant.host.summary();
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder")));
  const auto first_bd_seq = int_of(first->metric("bdSeq"));

  plant.broker.kill();
  ASSERT_TRUE(gateway.process().wait_for_line("mqtt: lost the broker", 10s)) << gateway.process().output();
  // Modbus goes on while the broker is away.
  ModbusClient modbus(gateway.port(), 1);
  ASSERT_TRUE(modbus.write_register(42, 1500).ok());
  EXPECT_EQ(plant.sim.field(1, "goal_position"), 1500);
  std::this_thread::sleep_for(300ms);  // a few reconnect attempts against a closed port

  plant.broker.start();
  SparkplugHost host(plant.broker.port());
  const auto again = host.wait(is(MessageType::NBirth), 15s);
  ASSERT_TRUE(again) << host.summary() << gateway.process().output();
  EXPECT_NE(int_of(again->metric("bdSeq")), first_bd_seq);
  const auto reborn = host.wait(is(MessageType::DBirth, "shoulder"));
  ASSERT_TRUE(reborn);
  EXPECT_EQ(int_of(reborn->metric("goal_position")), 1500);  // what happened meanwhile

  // A gateway that dies without a goodbye: the broker publishes its will, NDEATH with the bdSeq
  // of the NBIRTH it belongs to.
  gateway.process().signal(SIGKILL);
  const auto death = host.wait(is(MessageType::NDeath), 60s);
  ASSERT_TRUE(death) << host.summary();
  EXPECT_EQ(int_of(death->metric("bdSeq")), int_of(again->metric("bdSeq")));
}

// A command the broker delivered is carried out, in order, even when the broker dies while the
// gateway is still working through it: 1000 goal writes in one DCMD, each answered 5 ms late by
// the servo (at least 5 s of work, so that even a loaded machine kills the broker in the middle);
// the broker is killed once the first has reached the servo; the last value lands, and the next
// DBIRTH reports it.
TEST(Sparkplug, ADeliveredCommandIsCarriedOutWhenTheBrokerDiesMeanwhile) {
  Plant plant;
  const std::string yaml = gateway_yaml(plant.sim.pty(), plant.broker.port());
  auto gateway = GatewayProcess::with_config(plant.dir, yaml, 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"))) << plant.host.summary();
  ASSERT_EQ(plant.sim.control("late 1 5"), "ok");
  ModbusClient modbus(gateway.port(), 1);
  ASSERT_TRUE(modbus.write_register(42, 0).ok());  // a goal none of the commands has
  std::vector<sp::Metric> writes;
  for (int i = 0; i < 1000; ++i)
    writes.push_back(sp::Metric::int16("goal_position", static_cast<std::int16_t>(100 + i)));
  writes.push_back(sp::Metric::int16("goal_position", 2222));
  plant.host.command(MessageType::DCmd, kGroup, kNode, "shoulder", writes);
  ASSERT_TRUE(eventually([&] { return plant.sim.field(1, "goal_position") >= 100; })) << gateway.process().output();
  plant.broker.kill();
  EXPECT_NE(plant.sim.field(1, "goal_position"), 2222) << "all writes were done before the broker died";
  ASSERT_TRUE(eventually([&] { return plant.sim.field(1, "goal_position") == 2222; }, 60s, "the last goal"))
      << "goal " << plant.sim.field(1, "goal_position") << "\n"
      << gateway.process().output();

  plant.broker.start();
  SparkplugHost host(plant.broker.port());
  const auto reborn = host.wait(is(MessageType::DBirth, "shoulder"), 15s);
  ASSERT_TRUE(reborn) << host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(reborn->metric("goal_position")), 2222);
  EXPECT_EQ(text_of(reborn->metric("Gateway/Last Command")), "ok: goal_position := 2222");
}

TEST(Sparkplug, TlsAndCredentialsToTheBrokerAndARefusedPassword) {
  TempDir dir;
  const std::string certs = dir.file("certs");
  ASSERT_EQ(std::system((std::string(SMS_SOURCE_DIR) + "/tests/e2e/make_test_certs.sh " + certs).c_str()), 0);
  // mosquitto started as root reads its files as user mosquitto: let it.
  for (const auto& path : {dir.file(""), certs}) {
    std::filesystem::permissions(path, std::filesystem::perms::others_read | std::filesystem::perms::others_exec,
                                 std::filesystem::perm_options::add);
  }
  for (const auto& entry : std::filesystem::directory_iterator(certs)) {
    std::filesystem::permissions(entry.path(), std::filesystem::perms::others_read, std::filesystem::perm_options::add);
  }
  const std::string passwords = dir.file("passwords");
  std::ofstream(passwords) << "";
  ASSERT_EQ(std::system(("/usr/bin/mosquitto_passwd -b " + passwords + " gateway s3cret").c_str()), 0);
  ASSERT_EQ(std::system(("/usr/bin/mosquitto_passwd -b " + passwords + " scada h0st").c_str()), 0);
  std::filesystem::permissions(passwords, std::filesystem::perms::others_read, std::filesystem::perm_options::add);
  MosquittoBroker broker(dir, "allow_anonymous false\npassword_file " + passwords + "\ncafile " + certs +
                                  "/ca.crt\ncertfile " + certs + "/server.crt\nkeyfile " + certs + "/server.key\n");
  SimProcess sim(dir, "sim", {"--ids", "1-2"});
  SparkplugHost host(broker.port(), HostOptions{"scada", "h0st", certs + "/ca.crt"});
  std::ofstream(dir.file("gateway.password")) << "s3cret\n";
  std::ofstream(dir.file("wrong.password")) << "guess\n";

  const auto yaml = [&](const std::string& password_file) {
    return substitute(gateway_yaml(sim.pty(), broker.port(),
                                   "  username: gateway\n  password_file: " + password_file + "\n  tls: {ca: " + certs +
                                       "/ca.crt}\n"),
                      "127.0.0.1:" + std::to_string(broker.port()), "localhost:" + std::to_string(broker.port()));
  };
  {
    auto refused = GatewayProcess::with_config(dir, yaml(dir.file("wrong.password")), 1);
    EXPECT_TRUE(refused.process().wait_for_line("the broker refused the connection", 10s))
        << refused.process().output();
    EXPECT_FALSE(host.wait(is(MessageType::NBirth), 500ms));
  }
  auto gateway = GatewayProcess::with_config(dir, yaml(dir.file("gateway.password")), 1);
  ASSERT_TRUE(host.wait(is(MessageType::NBirth))) << host.summary() << gateway.process().output();
  ASSERT_TRUE(host.wait(is(MessageType::DBirth, "shoulder"))) << host.summary();
}

TEST(Sparkplug, TlsToAPlainBrokerIsLoggedAndModbusGoesOn) {
  TempDir dir;
  const std::string certs = dir.file("certs");
  ASSERT_EQ(std::system((std::string(SMS_SOURCE_DIR) + "/tests/e2e/make_test_certs.sh " + certs).c_str()), 0);
  MosquittoBroker broker(dir);  // plain MQTT: the gateway's TLS handshake gets MQTT bytes back
  SimProcess sim(dir, "sim", {"--ids", "1-2"});
  auto gateway = GatewayProcess::with_config(
      dir, gateway_yaml(sim.pty(), broker.port(), "  tls: {ca: " + certs + "/ca.crt}\n"), 1);
  ASSERT_TRUE(gateway.process().wait_for_line("mqtt: cannot connect to broker", 10s)) << gateway.process().output();
  // The MQTT failure can be logged before the first poll cycle has filled the cache (which
  // answers 0x0B until then): wait for it, as every cached read in these tests does.
  wait_until_polled(gateway.port(), 1);
  ModbusClient modbus(gateway.port(), 1);
  EXPECT_TRUE(modbus.read_input(56, 2).ok());
  std::this_thread::sleep_for(500ms);  // several attempts: logged once, no crash
  EXPECT_TRUE(modbus.read_input(56, 2).ok());
  // Each reason is logged once per outage (a TLS client against a plain broker may see the
  // handshake fail or the connection reset, depending on timing): at most those two lines for
  // the three or more attempts of these 500 ms.
  const std::string output = gateway.process().output();
  std::vector<std::string> reasons;
  for (std::size_t at = 0; (at = output.find("mqtt: cannot connect", at)) != std::string::npos; ++at) {
    reasons.push_back(output.substr(at, output.find('\n', at) - at));
  }
  EXPECT_GE(reasons.size(), 1u) << output;
  EXPECT_LE(reasons.size(), 2u) << output;
  for (std::size_t i = 1; i < reasons.size(); ++i) EXPECT_NE(reasons[i], reasons[0]) << output;
}

// What a host decodes, read by protoc rather than our decoder: every metric of NBIRTH, DBIRTH,
// NDATA and DDATA carries a timestamp (Sparkplug 3.0), bdSeq is an Int64 in long_value, the
// 32-bit counters UInt64 in long_value (read alike by the spec and Tahu), a signed field Int16 in
// int_value. The DDATA after a command reports the value read back: the servo clamps a goal of
// -100 to its angle limit 0, and that is what the host sees.
TEST(Sparkplug, ProtocReadsTimestampsAndTypesOnEveryBirthAndDataMetric) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  const auto nbirth = plant.host.wait(is(MessageType::NBirth));
  const auto dbirth = plant.host.wait(is(MessageType::DBirth, "shoulder"));
  ASSERT_TRUE(nbirth && dbirth) << plant.host.summary() << gateway.process().output();

  std::size_t from = plant.host.count();
  plant.host.command(MessageType::DCmd, kGroup, kNode, "shoulder", {sp::Metric::int16("goal_position", -100)});
  const auto ack = plant.host.wait(
      [](const SparkplugMessage& m) {
        return m.topic.type == MessageType::DData && m.metric("goal_position") != nullptr;
      },
      10s, from);
  ASSERT_TRUE(ack) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(plant.sim.field(1, "goal_position"), 0);
  EXPECT_EQ(int_of(ack->metric("goal_position")), 0);  // what the servo holds, not the -100 sent
  EXPECT_EQ(text_of(ack->metric("Gateway/Last Command")), "ok: goal_position := -100, reads back 0");

  from = plant.host.count();
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::boolean("Gateway/E-Stop", true)});
  const auto ndata = plant.host.wait(is(MessageType::NData), 10s, from);
  ASSERT_TRUE(ndata) << plant.host.summary();

  const std::vector<std::pair<std::string, const SparkplugMessage*>> messages{
      {"NBIRTH", &*nbirth}, {"DBIRTH", &*dbirth}, {"DDATA", &*ack}, {"NDATA", &*ndata}};
  for (const auto& [what, message] : messages) {
    const auto metrics = protoc_metrics(message->bytes, plant.dir);
    ASSERT_EQ(metrics.size(), message->payload.metrics.size()) << what;
    for (const auto& metric : metrics) {
      const std::string name = metric.count("name") ? metric.at("name") : "<no name>";
      EXPECT_TRUE(metric.count("timestamp")) << what << " " << name << " has no timestamp";
      EXPECT_TRUE(metric.count("datatype")) << what << " " << name << " has no datatype";
    }
  }
  const auto find = [&](const SparkplugMessage& message, const std::string& name) {
    for (const auto& metric : protoc_metrics(message.bytes, plant.dir)) {
      if (metric.count("name") && metric.at("name") == "\"" + name + "\"") return metric;
    }
    return ProtocMetric{};
  };
  const auto bd_seq = find(*nbirth, "bdSeq");
  EXPECT_EQ(bd_seq.count("datatype") ? bd_seq.at("datatype") : "", "4");  // Int64
  EXPECT_TRUE(bd_seq.count("long_value"));
  for (const std::string counter : {"Gateway/Replies OK", "Gateway/Timeouts"}) {
    const auto metric = find(*dbirth, counter);
    EXPECT_EQ(metric.count("datatype") ? metric.at("datatype") : "", "8") << counter;  // UInt64
    EXPECT_TRUE(metric.count("long_value")) << counter;
  }
  EXPECT_NE(std::get<std::uint64_t>(dbirth->metric("Gateway/Replies OK")->value), 0u);
  const auto goal = find(*ack, "goal_position");
  EXPECT_EQ(goal.count("datatype") ? goal.at("datatype") : "", "2");  // Int16
  EXPECT_EQ(goal.count("int_value") ? goal.at("int_value") : "", "0");
  const auto estop = find(*ndata, "Gateway/E-Stop");
  EXPECT_EQ(estop.count("boolean_value") ? estop.at("boolean_value") : "", "true");
}

// Safety: a DCMD value that does not fit the metric's birth datatype or the register map's value
// check (the console's, in the same words), or is of another kind (Boolean, Float, String for a
// position), is refused with a log line and nothing is written; the simulator's goal is the witness. An empty DCMD is
// logged too.
TEST(Sparkplug, DcmdValuesAreCheckedAgainstTheBirthTypeAndTheMapRangeBeforeAnyWrite) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()), 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"))) << plant.host.summary();
  ModbusClient modbus(gateway.port(), 1);
  ASSERT_TRUE(modbus.write_register(42, 2000).ok());
  ASSERT_EQ(plant.sim.field(1, "goal_position"), 2000);

  const auto refused = [&](sp::Metric metric, const std::string& expected) {
    const std::string result = command_result(plant.host, metric);
    EXPECT_NE(result.find(expected), std::string::npos) << metric.name << ": " << result;
    EXPECT_NE(result.find("nothing written"), std::string::npos) << result;
    EXPECT_TRUE(gateway.process().wait_for_line(expected, 5s)) << gateway.process().output();
    EXPECT_EQ(plant.sim.field(1, "goal_position"), 2000) << metric.name << " moved the servo";
  };
  // UInt16 40000 is no Int16: not taken as -25536 (a full-travel move to the limit).
  refused(sp::Metric::uint16("goal_position", 40000), "40000 does not fit Int16 (-32768..32767)");
  refused(sp::Metric::int16("goal_position", 31000),
          "value 31000 for goal_position (42) of table sts is outside -30719..30719");
  refused(sp::Metric::boolean("goal_position", true), "got Boolean true, the metric is Int16");
  refused(sp::Metric::of("goal_position", sp::DataType::Double, 1500.0), "got Double 1500, the metric is Int16");
  refused(sp::Metric::uint16("torque_enable", 300), "value 300 for torque_enable (40) of table sts is outside 0..128");

  // A command as the spec says to send it, without a datatype: read as the DBIRTH's Int16.
  auto untyped = sp::Metric::int16("goal_position", -7);
  untyped.type = sp::DataType::Unknown;
  plant.host.command(MessageType::DCmd, kGroup, kNode, "shoulder", {untyped});
  EXPECT_TRUE(eventually([&] { return plant.sim.field(1, "goal_position") == 0; }))  // clamped at 0
      << plant.sim.field(1, "goal_position") << "\n"
      << gateway.process().output();

  // A node command of the wrong kind: the e-stop takes a Boolean only.
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::uint16("Gateway/E-Stop", 1)});
  EXPECT_TRUE(gateway.process().wait_for_line("NCMD refused: Gateway/E-Stop: got UInt16 1, the metric is Boolean", 5s))
      << gateway.process().output();
  EXPECT_TRUE(modbus.write_register(42, 1000).ok());  // not latched

  // Nothing in it: logged, not silently dropped.
  plant.host.raw("spBv1.0/plant/DCMD/gw1/shoulder", {});
  EXPECT_TRUE(gateway.process().wait_for_line("carries no metric", 5s)) << gateway.process().output();
}

// bdSeq: +1 per CONNECT that went out (an outage with many refused TCP attempts costs one), kept
// in state_dir across a restart.
TEST(Sparkplug, BdSeqCountsConnectsSentAndSurvivesARestart) {
  Plant plant;
  const std::string state = plant.dir.file("state");
  const std::string yaml = gateway_yaml(plant.sim.pty(), plant.broker.port()) + "state_dir: \"" + state + "\"\n";
  std::optional<std::int64_t> first;
  {
    auto gateway = GatewayProcess::with_config(plant.dir, yaml, 1);
    const auto birth = plant.host.wait(is(MessageType::NBirth));
    ASSERT_TRUE(birth) << plant.host.summary() << gateway.process().output();
    first = int_of(birth->metric("bdSeq"));
    EXPECT_EQ(first, 0);  // a fresh state_dir
    gateway.process().signal(SIGTERM);
    ASSERT_EQ(gateway.process().wait_exit(10s), std::optional<int>{0}) << gateway.process().output();
  }
  std::size_t from = plant.host.count();
  auto gateway = GatewayProcess::with_config(plant.dir, yaml, 1);
  const auto restarted = plant.host.wait(is(MessageType::NBirth), 10s, from);
  ASSERT_TRUE(restarted) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(restarted->metric("bdSeq")), 1);
  std::ifstream file(state + "/sparkplug-bdseq");
  std::string stored;
  std::getline(file, stored);
  EXPECT_EQ(stored, "1");

  // The broker away for 1.5 s: at 100..400 ms backoff, several refused attempts; one CONNECT.
  plant.broker.kill();
  ASSERT_TRUE(gateway.process().wait_for_line("mqtt: lost the broker", 10s)) << gateway.process().output();
  std::this_thread::sleep_for(1500ms);
  plant.broker.start();
  SparkplugHost host(plant.broker.port());
  const auto again = host.wait(is(MessageType::NBirth), 15s);
  ASSERT_TRUE(again) << host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(again->metric("bdSeq")), 2);
}

// A safety state the gateway could not save is a node metric (docs/SAFETY.md), as it is discrete
// input 4 for a PLC: false at birth, true in NDATA once a save fails (state_dir stops being a
// directory while the gateway runs), false again once a retried save succeeds.
TEST(Sparkplug, AnUnsavedSafetyStateIsANodeMetric) {
  Plant plant;
  const std::string state = plant.dir.file("state");
  std::filesystem::create_directories(state);
  auto gateway = GatewayProcess::with_config(
      plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()) + "state_dir: \"" + state + "\"\n", 1);
  const auto birth = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(birth) << plant.host.summary() << gateway.process().output();
  ASSERT_NE(birth->metric("Gateway/Safety State Not Persisted"), nullptr) << plant.host.summary();
  EXPECT_EQ(int_of(birth->metric("Gateway/Safety State Not Persisted")), 0);
  const auto persistence_news = [](const SparkplugMessage& m) {
    return m.topic.type == MessageType::NData && m.metric("Gateway/Safety State Not Persisted") != nullptr;
  };

  std::filesystem::rename(state, state + ".away");
  std::ofstream(state) << "in the way\n";
  std::size_t from = plant.host.count();
  plant.host.command(MessageType::NCmd, kGroup, kNode, "", {sp::Metric::boolean("Gateway/E-Stop", true)});
  const auto unsaved = plant.host.wait(persistence_news, 10s, from);
  ASSERT_TRUE(unsaved) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(unsaved->metric("Gateway/Safety State Not Persisted")), 1);

  from = plant.host.count();
  std::filesystem::remove(state);
  std::filesystem::rename(state + ".away", state);
  const auto saved = plant.host.wait(persistence_news, 10s, from);
  ASSERT_TRUE(saved) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(saved->metric("Gateway/Safety State Not Persisted")), 0);
}

// A state file that does not hold a bdSeq, or a state_dir that cannot be written: logged, the
// node starts and counts in memory (a bdSeq is not worth a refused start).
TEST(Sparkplug, ABrokenBdSeqFileOrStateDirIsLoggedAndTheNodeGoesOn) {
  Plant plant;
  const std::string state = plant.dir.file("state");
  std::filesystem::create_directories(state);
  std::ofstream(state + "/sparkplug-bdseq") << "garbage\n";
  {
    auto gateway = GatewayProcess::with_config(
        plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port()) + "state_dir: \"" + state + "\"\n", 1);
    const auto birth = plant.host.wait(is(MessageType::NBirth));
    ASSERT_TRUE(birth) << plant.host.summary() << gateway.process().output();
    EXPECT_EQ(int_of(birth->metric("bdSeq")), 0);
    EXPECT_TRUE(gateway.process().wait_for_line("sparkplug-bdseq does not hold a bdSeq (0..255); starting at 0", 5s))
        << gateway.process().output();
  }
  // A state_dir that cannot be written is a configuration error: the gateway keeps its e-stop
  // latch there (docs/SAFETY.md), so it does not start without it.
  const std::string not_a_dir = plant.dir.file("plain-file");
  std::ofstream(not_a_dir) << "x";
  const std::string path = plant.dir.file("unwritable.yaml");
  std::ofstream(path) << gateway_yaml(plant.sim.pty(), plant.broker.port()) + "state_dir: \"" + not_a_dir +
                             "/state\"\n";
  ChildProcess refused({bin("sms-gateway"), "--config", path, "--listen", "127.0.0.1:0"});
  const auto status = refused.wait_exit(10s);
  ASSERT_TRUE(status.has_value()) << refused.output();
  EXPECT_EQ(*status, 2) << refused.output();
  EXPECT_NE(refused.output().find("state_dir " + not_a_dir + "/state: Not a directory"), std::string::npos)
      << refused.output();
}

// Primary host (Ignition's setup): no NBIRTH until the host's STATE says online; offline ends
// the session with NDEATH; a stale STATE (older timestamp) is ignored; online again: new births
// with the next bdSeq.
TEST(Sparkplug, PrimaryHostStateGatesTheBirths) {
  Plant plant;
  auto gateway = GatewayProcess::with_config(
      plant.dir, gateway_yaml(plant.sim.pty(), plant.broker.port(), "  primary_host_id: scada\n"), 1);
  ASSERT_TRUE(gateway.process().wait_for_line("waiting for primary host scada", 10s)) << gateway.process().output();
  EXPECT_FALSE(plant.host.wait(is(MessageType::NBirth), 1s)) << "born without the primary host";

  const std::uint64_t t0 = 1'700'000'000'000;
  plant.host.state("scada", true, t0);
  const auto birth = plant.host.wait(is(MessageType::NBirth));
  ASSERT_TRUE(birth) << plant.host.summary() << gateway.process().output();
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"))) << plant.host.summary();

  std::size_t from = plant.host.count();
  plant.host.state("scada", false, t0 + 1);
  const auto death = plant.host.wait(is(MessageType::NDeath), 10s, from);
  ASSERT_TRUE(death) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(death->metric("bdSeq")), int_of(birth->metric("bdSeq")));
  ASSERT_TRUE(gateway.process().wait_for_line("primary host scada went offline", 5s)) << gateway.process().output();
  // Reconnected (the retained offline STATE says wait): no births.
  EXPECT_FALSE(plant.host.wait(is(MessageType::NBirth), 1s, from)) << plant.host.summary();
  plant.host.state("scada", true, t0);  // older than the offline one: stale
  EXPECT_TRUE(gateway.process().wait_for_line("ignored a stale STATE of primary host scada", 5s))
      << gateway.process().output();
  EXPECT_FALSE(plant.host.wait(is(MessageType::NBirth), 500ms, from)) << plant.host.summary();

  plant.host.state("scada", true, t0 + 2);
  const auto reborn = plant.host.wait(is(MessageType::NBirth), 10s, from);
  ASSERT_TRUE(reborn) << plant.host.summary() << gateway.process().output();
  EXPECT_EQ(int_of(reborn->metric("bdSeq")), *int_of(birth->metric("bdSeq")) + 1);
  ASSERT_TRUE(plant.host.wait(is(MessageType::DBirth, "shoulder"), 10s, from)) << plant.host.summary();
  // A STATE that is not the 3.0 JSON: logged, ignored.
  const std::string legacy = "OFFLINE";
  plant.host.raw(sp::state_topic("scada"), std::vector<std::uint8_t>(legacy.begin(), legacy.end()));
  EXPECT_TRUE(gateway.process().wait_for_line("ignored the STATE of primary host scada: not a Sparkplug 3.0 STATE", 5s))
      << gateway.process().output();
}

}  // namespace
}  // namespace sms::e2e::sparkplug_test
