// `sms-gateway scan` as library code against the simulator: servos at non-default rates of
// each protocol's baud table, two servos on one ID, the configuration written from a scan.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "config/load.h"
#include "gateway/tools/tool_link.h"
#include "gateway/tools/tool_scan.h"
#include "simulator/simulated_bus.h"
#include "tests/gateway/tools/tool_test_support.h"

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;
using modbus_map::TableId;
using protocol::BusProtocol;
using tool_testing::one_servo;
using tool_testing::open_link;
using tool_testing::quiet;

std::vector<std::uint8_t> ids(unsigned first, unsigned last) {
  std::vector<std::uint8_t> list;
  for (unsigned id = first; id <= last; ++id) list.push_back(static_cast<std::uint8_t>(id));
  return list;
}

const ScanFinding* finding(const ScanReport& report, std::uint32_t baud, std::uint8_t id) {
  const auto found = std::find_if(report.found.begin(), report.found.end(),
                                  [&](const ScanFinding& f) { return f.baud == baud && f.id == id; });
  return found == report.found.end() ? nullptr : &*found;
}

// A scan waits for each ID only the frames' wire time and the protocol's usual return delay, and
// skips a rate whose probe stays unanswered: where the machine held the simulator past that
// during a scan (the simulator witnessed a hold of 100 ms or more) and it found fewer servos than
// `expected`, the scan is made again, at most three times (tests/README.md "Counting on a loaded
// machine").
Expected<ScanReport> scan_witnessed(ServoLink& link, const simulator::SimulatedBus& bus, const ScanOptions& scan,
                                    std::size_t expected) {
  for (int attempt = 1;; ++attempt) {
    const auto started = std::chrono::steady_clock::now();
    auto report = scan_bus(link, scan, quiet);
    if (!report || report->found.size() >= expected || attempt == 3) return report;
    const auto holds = bus.holds();
    const bool held = std::any_of(holds.begin(), holds.end(), [&](const simulator::Hold& hold) {
      return hold.ended >= started && hold.held >= 100ms;
    });
    if (!held) return report;
  }
}

TEST(Scan, FindsFeetechServosAtNonDefaultRatesAndSkipsSilentRates) {
  simulator::BusOptions options;
  options.servos = {{1, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {3, TableId::Sts, BusProtocol::Feetech, 500'000},
                    {7, TableId::Sts, BusProtocol::Feetech, 76'800}};  // 76800 needs termios2
  simulator::SimulatedBus bus(options);
  bus.start();
  auto link = open_link(bus.slave_path(), BusProtocol::Feetech, 1'000'000);
  ScanOptions scan;
  scan.bauds = {1'000'000, 500'000, 250'000, 76'800};
  scan.ids = ids(0, 10);
  scan.table = TableId::Sts;
  const auto report = scan_witnessed(*link, bus, scan, 3);
  ASSERT_TRUE(report) << report.error();
  ASSERT_EQ(report->found.size(), 3U) << format_scan(*report);
  EXPECT_NE(finding(*report, 1'000'000, 1), nullptr);
  EXPECT_NE(finding(*report, 500'000, 3), nullptr);
  const ScanFinding* slow = finding(*report, 76'800, 7);
  ASSERT_NE(slow, nullptr);
  EXPECT_FALSE(slow->conflict);
  // Identity as the servo holds it: the model word at addresses 3-4, low byte first as the SDKs
  // read it; firmware major.minor at 0-1 (docs/PROTOCOL.md §2.1).
  const auto memory = bus.read_memory(7, 0, 5);
  ASSERT_TRUE(memory);
  EXPECT_EQ(slow->identity.model, static_cast<std::uint16_t>((*memory)[4] << 8 | (*memory)[3]));
  EXPECT_EQ(slow->table, TableId::Sts);
  EXPECT_EQ(slow->identity.firmware, static_cast<std::uint16_t>((*memory)[0] << 8 | (*memory)[1]));
  EXPECT_EQ(report->skipped_bauds, std::vector<std::uint32_t>{250'000});
}

TEST(Scan, FindsD55dServosAtNonDefaultRates) {
  simulator::BusOptions options;
  options.servos = {{2, TableId::D55d, BusProtocol::D55d, 256'000}, {5, TableId::D55d, BusProtocol::D55d, 1'280'000}};
  simulator::SimulatedBus bus(options);
  bus.start();
  auto link = open_link(bus.slave_path(), BusProtocol::D55d, 115'200);
  ScanOptions scan;
  scan.bauds = {115'200, 256'000, 1'280'000};
  scan.ids = ids(1, 8);
  scan.table = TableId::D55d;
  const auto report = scan_witnessed(*link, bus, scan, 2);
  ASSERT_TRUE(report) << report.error();
  ASSERT_EQ(report->found.size(), 2U) << format_scan(*report);
  EXPECT_NE(finding(*report, 256'000, 2), nullptr);
  EXPECT_NE(finding(*report, 1'280'000, 5), nullptr);
}

TEST(Scan, FindsModbusServosAtRatesLibmodbusCannotSetItself) {
  simulator::BusOptions options;
  options.servos = {{1, TableId::Smsmb, BusProtocol::ModbusRtu, 256'000},
                    {4, TableId::Smsmb, BusProtocol::ModbusRtu, 56'000},
                    {9, TableId::Smsmb, BusProtocol::ModbusRtu, 14'400}};
  simulator::SimulatedBus bus(options);
  bus.start();
  auto link = open_link(bus.slave_path(), BusProtocol::ModbusRtu, 115'200);
  ScanOptions scan;
  scan.bauds = {256'000, 115'200, 56'000, 14'400};
  scan.ids = ids(1, 10);
  scan.table = TableId::Smsmb;
  const auto report = scan_witnessed(*link, bus, scan, 3);
  ASSERT_TRUE(report) << report.error();
  ASSERT_EQ(report->found.size(), 3U) << format_scan(*report);
  EXPECT_NE(finding(*report, 256'000, 1), nullptr);
  EXPECT_NE(finding(*report, 56'000, 4), nullptr);
  const ScanFinding* slow = finding(*report, 14'400, 9);
  ASSERT_NE(slow, nullptr);
  const auto memory = bus.read_memory(9, 0x00, 2);  // firmware version, servo version
  ASSERT_TRUE(memory);
  EXPECT_EQ(slow->identity.firmware, static_cast<std::uint16_t>((*memory)[0] << 8 | (*memory)[1]));
  EXPECT_EQ(slow->identity.model, static_cast<std::uint16_t>((*memory)[2] << 8 | (*memory)[3]));
}

TEST(Scan, FindsAServoWhoseAnswerComesLateOnASecondLook) {
  simulator::BusOptions options;
  options.servos = {{1, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {3, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {6, TableId::Sts, BusProtocol::Feetech, 1'000'000}};
  simulator::SimulatedBus bus(options);
  bus.start();
  // Servo 3 answers 30 ms late: past the scan's first wait (about 20 ms here), so its answer
  // lands in a later ID's window, and within the second look's longer wait.
  bus.set_reply_delay(3, 30ms);
  auto link = open_link(bus.slave_path(), BusProtocol::Feetech, 1'000'000);
  ScanOptions scan;
  scan.bauds = {1'000'000};
  scan.ids = ids(1, 8);
  std::vector<std::string> said;
  const auto report = scan_bus(*link, scan, [&](const std::string& line) { said.push_back(line); });
  ASSERT_TRUE(report) << report.error();
  ASSERT_EQ(report->found.size(), 3U) << format_scan(*report);
  EXPECT_EQ(report->found[0].id, 1);
  EXPECT_EQ(report->found[1].id, 3);  // listed in ID order although found last
  EXPECT_EQ(report->found[2].id, 6);
  EXPECT_FALSE(report->found[1].conflict) << report->found[1].note;
  EXPECT_NE(std::find_if(said.begin(), said.end(),
                         [](const std::string& line) { return line.find("ID 3 answered late") != std::string::npos; }),
            said.end());
}

TEST(Scan, ReportsTwoServosAnsweringOnOneId) {
  simulator::BusOptions options;
  options.servos = {{1, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {2, TableId::Sts, BusProtocol::Feetech, 1'000'000}};
  options.seed = 1;
  simulator::SimulatedBus bus(options);
  bus.start();
  bus.add_duplicate(2);
  auto link = open_link(bus.slave_path(), BusProtocol::Feetech, 1'000'000);
  ScanOptions scan;
  scan.bauds = {1'000'000};
  scan.ids = ids(1, 4);
  const auto report = scan_bus(*link, scan, quiet);
  ASSERT_TRUE(report) << report.error();
  const ScanFinding* single = finding(*report, 1'000'000, 1);
  const ScanFinding* doubled = finding(*report, 1'000'000, 2);
  ASSERT_NE(single, nullptr);
  ASSERT_NE(doubled, nullptr);
  EXPECT_FALSE(single->conflict);
  EXPECT_TRUE(doubled->conflict);
  EXPECT_NE(format_scan(*report).find("two or more servos answer on this ID"), std::string::npos);
}

TEST(Scan, ReportsTwoModbusServosOnOneAddress) {
  simulator::BusOptions options;
  options.servos = {{3, TableId::Smsmb, BusProtocol::ModbusRtu, 115'200}};
  options.seed = 1;
  simulator::SimulatedBus bus(options);
  bus.start();
  bus.add_duplicate(3);
  auto link = open_link(bus.slave_path(), BusProtocol::ModbusRtu, 115'200);
  ScanOptions scan;
  scan.bauds = {115'200};
  scan.ids = ids(2, 4);
  scan.table = TableId::Smsmb;
  const auto report = scan_bus(*link, scan, quiet);
  ASSERT_TRUE(report) << report.error();
  ASSERT_EQ(report->found.size(), 1U) << format_scan(*report);
  EXPECT_TRUE(report->found[0].conflict);
}

TEST(Scan, RefusesARateOutsideTheProtocolsTable) {
  simulator::SimulatedBus bus(one_servo({1, TableId::Sts, BusProtocol::Feetech, 1'000'000}));
  bus.start();
  auto link = open_link(bus.slave_path(), BusProtocol::Feetech, 1'000'000);
  ScanOptions scan;
  scan.bauds = {123'456};
  const auto report = scan_bus(*link, scan, quiet);
  ASSERT_FALSE(report);
  EXPECT_NE(report.error().find("123456"), std::string::npos) << report.error();
  EXPECT_NE(report.error().find("1000000"), std::string::npos) << report.error();  // lists the valid rates
}

TEST(Scan, WritesAConfigurationTheGatewayLoads) {
  simulator::BusOptions options;
  options.servos = {{1, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {2, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {0, TableId::Sts, BusProtocol::Feetech, 1'000'000},
                    {6, TableId::Sts, BusProtocol::Feetech, 115'200}};
  simulator::SimulatedBus bus(options);
  bus.start();
  auto link = open_link(bus.slave_path(), BusProtocol::Feetech, 1'000'000);
  ScanOptions scan;
  scan.bauds = {1'000'000, 115'200};
  scan.ids = ids(0, 8);
  const auto report = scan_bus(*link, scan, quiet);
  ASSERT_TRUE(report) << report.error();
  const std::string yaml = scan_config_yaml(*report, link->settings());
  const auto config = config::load_config_string(yaml, "<scan>");
  ASSERT_TRUE(config) << config.error().to_string() << "\n" << yaml;
  ASSERT_EQ(config->buses.size(), 1U);
  EXPECT_EQ(config->buses[0].baud, 1'000'000U);
  EXPECT_EQ(config->buses[0].device, bus.slave_path());
  ASSERT_EQ(config->servos.size(), 3U) << yaml;
  EXPECT_EQ(config->servos[0].servo_id, 0);  // ID 0 cannot be a unit: the first free one stands in
  EXPECT_EQ(config->servos[0].unit_id, 3);
  EXPECT_EQ(config->servos[1].servo_id, 1);
  EXPECT_EQ(config->servos[1].unit_id, 1);
  // The servo at the other rate is named with the command that moves it.
  EXPECT_NE(yaml.find("--id 6 --new-baud 1000000"), std::string::npos) << yaml;
}

// IDs 1..count, sts, feetech, 1 Mbaud.
simulator::BusOptions sts_servos(std::uint8_t count) {
  simulator::BusOptions options;
  for (std::uint8_t id = 1; id <= count; ++id)
    options.servos.push_back({id, TableId::Sts, BusProtocol::Feetech, 1'000'000});
  return options;
}

// A link at 1 Mbaud with the scan's default adapter latency (5 ms).
std::unique_ptr<ServoLink> default_scan_link(const std::string& device) {
  auto link = open_link(device, BusProtocol::Feetech, 1'000'000);
  link->set_latency(5ms);
  return link;
}

// A host that is descheduled between two requests (a loaded edge box): the link works as
// ever, but each PING leaves only after a pause, so a late answer lands between two requests.
class PausingBeforeEachPing final : public ServoLink {
 public:
  PausingBeforeEachPing(ServoLink& link, std::chrono::milliseconds pause) : link_(link), pause_(pause) {}
  Expected<Ok> open() override { return link_.open(); }
  Expected<Ok> set_baud(std::uint32_t baud) override { return link_.set_baud(baud); }
  const LinkSettings& settings() const override { return link_.settings(); }
  void set_attempts(unsigned attempts) override { link_.set_attempts(attempts); }
  void set_latency(std::chrono::milliseconds latency) override { link_.set_latency(latency); }
  LinkAnswer ping(std::uint8_t id) override {
    std::this_thread::sleep_for(pause_);
    return link_.ping(id);
  }
  LinkAnswer read(std::uint8_t id, std::uint16_t address, std::uint16_t count) override {
    return link_.read(id, address, count);
  }
  LinkAnswer write(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> data) override {
    return link_.write(id, address, data);
  }
  LinkAnswer instruction(std::uint8_t id, std::uint8_t code) override { return link_.instruction(id, code); }
  std::chrono::nanoseconds wire_time(std::size_t bytes) const override { return link_.wire_time(bytes); }

 private:
  ServoLink& link_;
  std::chrono::milliseconds pause_;
};

// Servo 3 answers 15 ms late, after the scan's wait for it; the host pauses 40 ms before the
// next PING, so the answer waits on the line and is dropped unread when that PING goes out. The
// scan knows only that bytes were dropped: it asks the ID before again, waiting longer.
TEST(Scan, AnAnswerDroppedBeforeTheNextPingGetsItsIdASecondLook) {
  simulator::SimulatedBus bus(sts_servos(4));
  bus.start();
  bus.set_reply_delay(3, 15ms);  // past the scan's default 5 ms
  auto link = default_scan_link(bus.slave_path());
  PausingBeforeEachPing paused(*link, 40ms);
  ScanOptions scan;
  scan.bauds = {1'000'000};
  scan.ids = ids(1, 6);
  std::vector<std::string> said;
  const auto report = scan_bus(paused, scan, [&](const std::string& line) { said.push_back(line); });
  ASSERT_TRUE(report) << report.error();
  ASSERT_NE(finding(*report, 1'000'000, 3), nullptr) << format_scan(*report);
  EXPECT_EQ(report->found.size(), 4U) << format_scan(*report);
  EXPECT_NE(std::find(said.begin(), said.end(), " 1000000 bit/s: ID 3 answered late; found on a second look"),
            said.end());
}

// Every ID at 1 Mbaud with six servos on the line and the scan's default adapter latency
// (5 ms); prints the time it took (the README's figure), without asserting on it.
TEST(Scan, EveryIdAtOneMegabaudFindsTheSixServos) {
  simulator::SimulatedBus bus(sts_servos(6));
  bus.start();
  auto link = default_scan_link(bus.slave_path());
  ScanOptions scan;
  scan.bauds = {1'000'000};
  const auto report = scan_witnessed(*link, bus, scan, 6);
  ASSERT_TRUE(report) << report.error();
  EXPECT_EQ(report->found.size(), 6U) << format_scan(*report);
  EXPECT_EQ(report->ids_per_baud, 254U);
  std::cout << "scan of 254 IDs at 1000000 bit/s: " << report->elapsed.count() << " ms\n";
  RecordProperty("scan_254_ids_1mbaud_ms", static_cast<int>(report->elapsed.count()));
}

}  // namespace
}  // namespace sms::gateway
