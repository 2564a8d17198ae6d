// What survives a restart, end to end (docs/SAFETY.md "What survives a restart" and "When the
// state cannot be saved"): the real sms-gateway killed (SIGKILL: nothing sent, nothing written
// at the end) and started again on the same state_dir, the real sms-sim as the witness.
// - a safe stop owed to a servo that was silent when it ran (an e-stop, or the console's "stop
//   the bus") is still owed after the restart: sent before anything else, whatever on_start
//   says, and motion to that servo is refused until it has taken it;
// - a safety.state that is not a complete state of the exact schema latches the e-stop at start,
//   which stops the servo, and the log says why, where and what to do;
// - a state that cannot be saved is shown (gateway unit discrete input 4, /metrics, /healthz)
//   until a save succeeds, and what that save kept survives the next kill.
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/stat.h>

#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>

#include "tests/e2e/safety_support.h"
#include "tests/support/eventually.h"
#include "tests/support/metrics_http_client.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

constexpr int kStateNotPersistedInput = 4;  // discrete input of the gateway unit

// The number after `marker` in the first line of `process` holding it.
std::uint16_t port_after(ChildProcess& process, const std::string& marker) {
  const auto line = process.wait_for_line(marker, 15s);
  if (!line) throw std::runtime_error("no line with '" + marker + "':\n" + process.output());
  return static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
}

std::string file_text(const std::string& path) {
  std::ifstream in(path);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

// Servo 1 of one protocol on a bus WITHOUT a watchdog (so on_start is keep: nothing but an owed
// stop or a latch stops a servo at start), a state_dir, the metrics endpoint; killed and started
// again at will. `more_yaml` adds top-level keys (the console).
class RestartCell {
 public:
  explicit RestartCell(const Protocol& protocol, std::string more_yaml = {})
      : protocol_(protocol), more_yaml_(std::move(more_yaml)) {
    sim_ = std::make_unique<SimProcess>(dir_, "sim", std::vector<std::string>{"--servo", protocol_.sim_servo});
    // A d55d motor stops by itself 500 ms after its last instruction (address 17): off, so the
    // witness shows what the gateway did, not what the motor's own heartbeat did.
    if (protocol_.bus_protocol == "d55d") {
      EXPECT_EQ(sim_->control("set 1 17 00"), "ok");
    }
    ::mkdir(state_dir().c_str(), 0755);
    start_gateway();
  }

  // `polled`: wait until servo 1 answered a poll (not when it is offline at start).
  void start_gateway(bool polled = true) {
    const std::string yaml = config_for(protocol_, sim_->pty(), ", offline_probe_period_ms: 100") + more_yaml_ +
                             "state_dir: \"" + state_dir() + "\"\n";
    gateway_.reset();
    gateway_ =
        std::make_unique<GatewayProcess>(GatewayProcess::with_config(dir_, yaml, 1, {"--metrics", "127.0.0.1:0"}));
    metrics_port_ = port_after(gateway_->process(), "/healthz on http://127.0.0.1:");
    if (polled) wait_until_polled(gateway_->port(), kUnit);
  }
  void kill_gateway() {
    gateway_->process().signal(SIGKILL);
    ASSERT_TRUE(gateway_->process().wait_exit(10s).has_value());
  }

  // Puts servo 1 in speed mode, turning.
  void spin() {
    ModbusClient plc(port(), kUnit);
    for (const Write& write : protocol_.spin) {
      const auto answer = plc.write_register(write.address, write.value);
      ASSERT_TRUE(answer.ok()) << "write " << write.address << " := " << write.value << ": " << answer.error;
    }
    ASSERT_TRUE(eventually([&] { return turning(); }, "servo 1 turning")) << log();
  }
  bool turning() { return sim_->field(1, "present_speed") != 0; }
  // Stopped by the owed stop: torque off where the table has a torque switch, speed 0 on d55d.
  bool took_torque_off() {
    return !turning() && (protocol_.torque_field.empty() || sim_->field(1, protocol_.torque_field) == 0);
  }

  std::uint16_t input(int address) {
    ModbusClient hmi(port(), kGateway);
    const auto answer = hmi.read_input(address, 1);
    return answer.ok() ? answer.values[0] : 0xFFFF;
  }
  int discrete(int address) {
    ModbusClient hmi(port(), kGateway);
    const auto answer = hmi.read_discrete(address, 1);
    return answer.ok() ? answer.values[0] : -1;
  }
  int estop(bool latch) {
    ModbusClient hmi(port(), kGateway);
    return hmi.write_coils(kEStopCoil, {static_cast<std::uint8_t>(latch ? 1 : 0)}).exception;
  }
  int motion_write() {
    ModbusClient plc(port(), kUnit);
    return plc.write_register(protocol_.goal.address, protocol_.goal.value).exception;
  }
  HttpResponse http(const std::string& path) { return http_request(metrics_port_, "GET", path); }
  std::string metric(const std::string& name) { return parse_exposition(http("/metrics").body).value(name); }

  // The state file names servo 1 of bus `line` as owed, for `why`.
  bool state_file_owes_servo_1(const std::string& why) {
    return file_text(state_file()).find("{bus: line, servo: 1, why: " + why) != std::string::npos;
  }

  const TempDir& dir() const { return dir_; }
  std::string state_dir() const { return dir_.file("state"); }
  std::string state_file() const { return dir_.file("state") + "/safety.state"; }
  SimProcess& sim() { return *sim_; }
  GatewayProcess& gateway() { return *gateway_; }
  std::uint16_t port() const { return gateway_->port(); }
  std::string log() { return gateway_->process().output(); }

 private:
  const Protocol& protocol_;
  std::string more_yaml_;
  TempDir dir_;
  std::unique_ptr<SimProcess> sim_;
  std::unique_ptr<GatewayProcess> gateway_;
  std::uint16_t metrics_port_ = 0;
};

// The protocols whose simulated servo can be put offline: sts, d55d, smsmb.
const std::vector<Protocol> kOwedProtocols{kSafetyProtocols[0], kSafetyProtocols[2], kSafetyProtocols[3]};

class OwedStopAcrossARestart : public testing::TestWithParam<Protocol> {
 protected:
  // Servo 1 turning and offline, the e-stop latched (its stop cannot reach servo 1: owed) and
  // reset, then the gateway killed.
  void owe_and_kill(RestartCell& cell) {
    cell.spin();
    ASSERT_EQ(cell.sim().control("offline 1"), "ok");
    cell.estop(true);  // answered 0x04 on modbus-rtu (its one write failed), OK elsewhere: latched either way
    ASSERT_TRUE(eventually([&] { return cell.input(kOwedStops) == 1; }, "servo 1 owed its stop")) << cell.log();
    ASSERT_EQ(cell.estop(false), 0) << cell.log();
    ASSERT_TRUE(eventually([&] { return cell.state_file_owes_servo_1("e-stop"); }, "the owed stop in the state file"))
        << file_text(cell.state_file());
    cell.kill_gateway();
    ASSERT_TRUE(cell.turning()) << "the witness: nothing reached the deaf servo, and a killed gateway sends nothing";
  }
};

// The tester's case: the servo is back before the gateway is. The owed stop is its first
// transaction; nothing else (on_start is keep on this bus) would have stopped it.
TEST_P(OwedStopAcrossARestart, IsSentAtStartWhenTheServoIsBack) {
  RestartCell cell(GetParam());
  owe_and_kill(cell);
  ASSERT_EQ(cell.sim().control("online 1"), "ok");
  ASSERT_TRUE(cell.turning()) << "the witness: online again, still turning";

  cell.start_gateway();
  EXPECT_TRUE(eventually([&] { return cell.took_torque_off(); }, "servo 1's torque off")) << cell.log();
  EXPECT_TRUE(cell.gateway().process().wait_for_line("servo 1 was owed its safe stop (e-stop) before the restart", 2s))
      << cell.log();
  EXPECT_TRUE(cell.gateway().process().wait_for_line("took its owed safe stop", 2s)) << cell.log();
  EXPECT_TRUE(eventually([&] { return cell.input(kOwedStops) == 0; }, "nothing owed"));
  EXPECT_TRUE(eventually([&] { return !cell.state_file_owes_servo_1("e-stop"); }, "the taken stop off the state file"))
      << file_text(cell.state_file());
  EXPECT_EQ(cell.motion_write(), 0) << cell.log();
}

// The servo is still silent when the gateway starts again: the stop stays owed, visible, and
// motion to the servo is refused until it answers and takes it.
TEST_P(OwedStopAcrossARestart, RefusesMotionUntilTheServoTakesIt) {
  RestartCell cell(GetParam());
  owe_and_kill(cell);
  cell.start_gateway(false);
  EXPECT_EQ(cell.input(kOwedStops), 1) << cell.log();
  EXPECT_EQ(cell.input(kBus0OwedStops), 1);
  EXPECT_EQ(cell.discrete(kOwedStopInput), 1);
  EXPECT_EQ(cell.motion_write(), 0x04) << cell.log();
  EXPECT_TRUE(cell.turning());

  ASSERT_EQ(cell.sim().control("online 1"), "ok");
  EXPECT_TRUE(eventually([&] { return cell.took_torque_off(); }, "servo 1's torque off")) << cell.log();
  EXPECT_TRUE(eventually([&] { return cell.input(kOwedStops) == 0; }, "nothing owed"));
  EXPECT_EQ(cell.discrete(kOwedStopInput), 0);
  EXPECT_TRUE(eventually([&] { return cell.motion_write() == 0; }, "a motion write accepted")) << cell.log();
}

INSTANTIATE_TEST_SUITE_P(EveryProtocol, OwedStopAcrossARestart, testing::ValuesIn(kOwedProtocols), protocol_name);

// --- the console's "stop the bus" --------------------------------------------------------------

// A console login over plain HTTP: the session cookie and the CSRF token a POST needs.
struct ConsoleSession {
  std::string cookie;
  std::string csrf;
};

HttpResponse console_post(std::uint16_t port, const std::string& path, const std::string& body,
                          const ConsoleSession* session = nullptr) {
  HttpConnection connection(port);
  std::string request = "POST " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n" +
                        "Content-Type: application/json\r\nContent-Length: " + std::to_string(body.size()) + "\r\n";
  if (session != nullptr) request += "Cookie: " + session->cookie + "\r\nX-CSRF-Token: " + session->csrf + "\r\n";
  connection.send(request + "\r\n" + body);
  auto response = connection.read_response(false, 10s);
  if (!response) throw std::runtime_error("POST " + path + ": no complete response");
  return *response;
}

ConsoleSession console_login(std::uint16_t port, const std::string& user, const std::string& password) {
  const auto answer =
      console_post(port, "/api/login", R"({"user": ")" + user + R"(", "password": ")" + password + "\"}");
  if (answer.status != 200) throw std::runtime_error("login refused: " + answer.body);
  std::smatch csrf;
  if (!std::regex_search(answer.body, csrf, std::regex(R"re("csrf":"([^"]+)")re"))) {
    throw std::runtime_error("no csrf in " + answer.body);
  }
  const std::string cookie = answer.header("set-cookie");
  return ConsoleSession{cookie.substr(0, cookie.find(';')), csrf[1]};
}

std::string password_hash(const std::string& password) {
  ChildProcess hash({"/bin/sh", "-c", "echo '" + password + "' | '" + bin("sms-gateway") + "' hash-password"});
  if (hash.wait_exit(30s) != 0) throw std::runtime_error("hash-password failed:\n" + hash.output());
  std::string line;
  std::istringstream out(hash.output());
  for (std::string next; std::getline(out, next);) {
    if (next.rfind("$argon2", 0) == 0) line = next;
  }
  if (line.empty()) throw std::runtime_error("hash-password printed no hash:\n" + hash.output());
  return line;
}

// The tester's second case: a servo silent while the console stops its bus to commission the
// line, the gateway killed before the bus is started again. The stop it could not take is owed
// after the restart, and sent first.
TEST(OwedStopAcrossARestartFromTheConsole, StopTheBusThenKill) {
  const Protocol& sts = kSafetyProtocols[0];
  const std::string console =
      "console:\n  listen: \"127.0.0.1:0\"\n  users:\n    - {name: eng, role: engineer, "
      "password_hash: \"" +
      password_hash("correct horse") + "\"}\n";
  RestartCell cell(sts, console);
  const std::uint16_t console_port =
      port_after(cell.gateway().process(), "serving the browser console on http://127.0.0.1:");
  cell.spin();
  ASSERT_EQ(cell.sim().control("offline 1"), "ok");
  const ConsoleSession session = console_login(console_port, "eng", "correct horse");
  const auto stop =
      console_post(console_port, "/api/commission/stop-bus", R"({"bus": "line", "confirm": true})", &session);
  ASSERT_LT(stop.status, 300) << stop.body;
  ASSERT_TRUE(eventually([&] { return cell.input(kOwedStops) == 1; }, "servo 1 owed its stop")) << cell.log();
  ASSERT_TRUE(eventually([&] { return cell.state_file_owes_servo_1("commissioning"); }, "the owed stop on disk"))
      << file_text(cell.state_file());
  cell.kill_gateway();
  ASSERT_EQ(cell.sim().control("online 1"), "ok");
  ASSERT_TRUE(cell.turning()) << "the witness: the stop never reached it";

  cell.start_gateway();
  EXPECT_TRUE(eventually([&] { return cell.took_torque_off(); }, "servo 1's torque off")) << cell.log();
  EXPECT_TRUE(
      cell.gateway().process().wait_for_line("servo 1 was owed its safe stop (commissioning) before the restart", 2s))
      << cell.log();
  EXPECT_TRUE(eventually([&] { return cell.input(kOwedStops) == 0; }, "nothing owed"));
}

// --- damaged state files -----------------------------------------------------------------------

struct Damage {
  std::string name;
  std::optional<std::string> text;  // nullopt: safety.state is a directory
  std::string reason;               // in the log line
};
void PrintTo(const Damage& damage, std::ostream* out) { *out << damage.name; }

const std::vector<Damage> kDamages{
    {"Empty", "", "it is empty"},
    {"CutMidValue", "estop_latched: tr", "it misses the key `tripped_watchdogs`"},
    {"UnknownKeysOnly", "colour: blue\nsize: 3\n", "it has an unknown key `colour`"},
    {"MisspeltKey", "estop_latch: true\n", "it has an unknown key `estop_latch`"},
    {"Maybe", "estop_latched: maybe\ntripped_watchdogs: []\n", "estop_latched is `maybe`, not true or false"},
    {"AList", "- estop_latched: false\n- tripped_watchdogs: []\n", "it is a list, not a map of its keys"},
    {"ADirectory", std::nullopt, "is not a regular file (a directory); remove it"},
};

class DamagedStateAtStart : public testing::TestWithParam<Damage> {};

// A servo turning, the gateway killed, its state file damaged: the next start latches the
// e-stop (which stops the servo: the witness), refuses motion, and says why in one line.
TEST_P(DamagedStateAtStart, LatchesStopsAndSaysWhy) {
  const Protocol& sts = kSafetyProtocols[0];
  RestartCell cell(sts);
  cell.spin();
  cell.kill_gateway();
  std::filesystem::remove(cell.state_file());
  if (GetParam().text) {
    std::ofstream(cell.state_file(), std::ios::binary) << *GetParam().text;
  } else {
    std::filesystem::create_directory(cell.state_file());
  }
  ASSERT_TRUE(cell.turning());

  cell.start_gateway();
  EXPECT_EQ(cell.input(kEStopLatchedRegister), 1) << cell.log();
  EXPECT_TRUE(eventually([&] { return !cell.turning(); }, "servo 1 stopped by the latch")) << cell.log();
  EXPECT_EQ(cell.motion_write(), 0x04);
  const auto line = cell.gateway().process().wait_for_line("the e-stop is LATCHED as a precaution", 2s);
  ASSERT_TRUE(line) << cell.log();
  EXPECT_NE(line->find(cell.state_file()), std::string::npos) << *line;
  EXPECT_NE(line->find(GetParam().reason), std::string::npos) << *line;
  EXPECT_NE(line->find("reset the e-stop (gateway unit coil 1 := 0)"), std::string::npos) << *line;
}

INSTANTIATE_TEST_SUITE_P(EveryDamage, DamagedStateAtStart, testing::ValuesIn(kDamages),
                         [](const testing::TestParamInfo<Damage>& info) { return info.param.name; });

// A tripped watchdog of a bus that no longer exists is stale, not damage: a warning, no latch.
TEST(StaleStateAtStart, ATripOfABusThatIsGoneIsAWarning) {
  const Protocol& sts = kSafetyProtocols[0];
  RestartCell cell(sts);
  cell.kill_gateway();
  std::ofstream(cell.state_file()) << "version: 2\nestop_latched: false\ntripped_watchdogs: [gone]\nowed_stops: []\n";
  cell.start_gateway();
  EXPECT_EQ(cell.input(kEStopLatchedRegister), 0) << cell.log();
  EXPECT_TRUE(cell.gateway().process().wait_for_line("names a tripped watchdog on bus `gone`", 2s)) << cell.log();
  EXPECT_EQ(cell.motion_write(), 0) << cell.log();
}

// --- a state that cannot be saved ----------------------------------------------------------------

// state_dir stops being a directory while the gateway runs: its path becomes a regular file.
// Creating `<state_dir>/safety.state.new` then fails with ENOTDIR whoever asks — root included,
// which chmod would not stop (root bypasses permission bits) — and nothing needs mounting.
TEST(StateNotPersisted, IsShownUntilASaveSucceeds) {
  const Protocol& sts = kSafetyProtocols[0];
  RestartCell cell(sts);
  EXPECT_EQ(cell.discrete(kStateNotPersistedInput), 0);
  EXPECT_EQ(cell.metric("sms_gateway_safety_state_not_persisted"), "0");
  EXPECT_EQ(cell.http("/healthz").status, 200);
  cell.spin();
  std::filesystem::rename(cell.state_dir(), cell.state_dir() + ".away");
  std::ofstream(cell.state_dir()) << "in the way\n";

  EXPECT_EQ(cell.estop(true), 0) << cell.log();  // the stop is done; only the keeping failed
  EXPECT_TRUE(eventually([&] { return !cell.turning(); }, "servo 1 stopped by the e-stop"));
  EXPECT_EQ(cell.discrete(kStateNotPersistedInput), 1) << cell.log();
  EXPECT_EQ(cell.metric("sms_gateway_safety_state_not_persisted"), "1");
  const auto health = cell.http("/healthz");
  EXPECT_EQ(health.status, 503);
  EXPECT_NE(
      health.body.find("safety state not persisted: cannot create " + cell.state_file() + ".new: Not a directory"),
      std::string::npos)
      << health.body;
  EXPECT_TRUE(cell.gateway().process().wait_for_line("SAFETY STATE NOT PERSISTED", 2s)) << cell.log();

  std::filesystem::remove(cell.state_dir());
  std::filesystem::rename(cell.state_dir() + ".away", cell.state_dir());
  EXPECT_TRUE(eventually([&] { return cell.discrete(kStateNotPersistedInput) == 0; }, "a retried save")) << cell.log();
  EXPECT_EQ(cell.metric("sms_gateway_safety_state_not_persisted"), "0");
  EXPECT_EQ(cell.http("/healthz").status, 200);
  EXPECT_TRUE(cell.gateway().process().wait_for_line("the safety state is kept in", 2s)) << cell.log();

  // What the retry saved is what the next start finds.
  cell.kill_gateway();
  cell.start_gateway();
  EXPECT_EQ(cell.input(kEStopLatchedRegister), 1) << cell.log();
  EXPECT_EQ(cell.motion_write(), 0x04);
}

}  // namespace
}  // namespace sms::e2e
