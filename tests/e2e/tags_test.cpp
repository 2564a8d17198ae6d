// `sms-gateway tags` against the running plant (tests/e2e/plant.h): rows of its CSV read with a
// real client at the row's address and function code, and once with mbpoll's own arguments from
// the row (mbpoll counts from 1), each value compared with the simulator's field. And the CLI's
// refusals: a bad --format, a missing configuration file.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "tests/e2e/plant.h"
#include "tests/support/child_process.h"
#include "tests/support/modbus_client.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

namespace {

using namespace std::chrono_literals;

Finished run(const std::vector<std::string>& argv, std::chrono::milliseconds timeout = 60s) {
  return run_to_end(argv, timeout);
}

// The CSV's rows as header -> value (RFC 4180: quoted fields may hold commas and doubled quotes).
std::vector<std::map<std::string, std::string>> rows_of(const std::string& csv) {
  std::vector<std::vector<std::string>> cells(1);
  std::string field;
  bool quoted = false;
  for (std::size_t i = 0; i < csv.size(); ++i) {
    const char c = csv[i];
    if (quoted && c == '"' && i + 1 < csv.size() && csv[i + 1] == '"') {
      field += '"';
      ++i;
    } else if (c == '"') {
      quoted = !quoted;
    } else if (!quoted && c == ',') {
      cells.back().push_back(std::exchange(field, {}));
    } else if (!quoted && c == '\r' && i + 1 < csv.size() && csv[i + 1] == '\n') {
      cells.back().push_back(std::exchange(field, {}));
      cells.emplace_back();
      ++i;
    } else {
      field += c;
    }
  }
  std::vector<std::map<std::string, std::string>> rows;
  for (std::size_t r = 1; r < cells.size(); ++r) {
    if (cells[r].size() != cells[0].size()) continue;  // the empty line after the last CRLF
    std::map<std::string, std::string> row;
    for (std::size_t c = 0; c < cells[0].size(); ++c) row[cells[0][c]] = cells[r][c];
    rows.push_back(std::move(row));
  }
  return rows;
}

const std::map<std::string, std::string>* find_row(const std::vector<std::map<std::string, std::string>>& rows,
                                                   const std::string& unit, const std::string& space,
                                                   const std::string& name) {
  for (const auto& row : rows) {
    if (row.at("unit") == unit && row.at("space") == space && row.at("name") == name) return &row;
  }
  return nullptr;
}

// The value at the row's address, read with the row's read function.
long read_row(ModbusClient& client, const std::map<std::string, std::string>& row) {
  client.set_unit(std::stoi(row.at("unit")));
  const int address = std::stoi(row.at("address"));
  const int fc = std::stoi(row.at("read_fc"));
  if (fc == 1 || fc == 2) {
    const auto bits = fc == 1 ? client.read_coils(address, 1) : client.read_discrete(address, 1);
    return bits.or_throw("FC0" + row.at("read_fc"))[0] ? 1 : 0;
  }
  const auto registers = fc == 3 ? client.read_holding(address, 1) : client.read_input(address, 1);
  const std::uint16_t value = registers.or_throw("FC0" + row.at("read_fc"))[0];
  return row.at("data_type") == "int16" ? static_cast<std::int16_t>(value) : value;
}

TEST(Tags, CsvRowsReadTheSimulatorsFieldsThroughTheGateway) {
  Plant plant;
  const std::string config = plant.dir().file("gateway.yaml");
  const Finished tags = run(
      {bin("sms-gateway"), "tags", "--config", config, "--format", "csv", "--output", plant.dir().file("tags.csv")});
  ASSERT_EQ(tags.status, 0) << tags.output;
  std::ifstream file(plant.dir().file("tags.csv"), std::ios::binary);
  const std::string csv((std::istreambuf_iterator<char>(file)), std::istreambuf_iterator<char>());
  const auto rows = rows_of(csv);
  ASSERT_GT(rows.size(), 100U);

  struct Probe {
    const char* unit;
    const char* space;
    const char* name;  // the row's name, and the simulator's field
    SimProcess& sim;
    int servo_id;
  };
  const Probe probes[] = {
      {"1", "holding", "max_angle_limit", plant.arm(), 1},    // sts native, FC03
      {"3", "input", "present_voltage", plant.arm(), 3},      // smsmb profile, FC04 at 0x104
      {"11", "holding", "max_temperature", plant.base(), 1},  // d55d, FC03
      {"1", "coil", "torque_enable", plant.arm(), 1},         // FC01
  };
  ModbusClient client(plant.port(), 1);
  for (const Probe& probe : probes) {
    const auto* row = find_row(rows, probe.unit, probe.space, probe.name);
    ASSERT_NE(row, nullptr) << probe.unit << " " << probe.space << " " << probe.name << "\n" << csv;
    EXPECT_EQ(read_row(client, *row), probe.sim.field(probe.servo_id, probe.name))
        << probe.unit << " " << probe.space << " " << probe.name;
  }

  // The gateway unit's rows come from the constants it is served with.
  const auto* buses = find_row(rows, "255", "input", "bus_count");
  ASSERT_NE(buses, nullptr);
  EXPECT_EQ(read_row(client, *buses), 2);
  const auto* servos = find_row(rows, "255", "input", "servo_count");
  ASSERT_NE(servos, nullptr);
  EXPECT_EQ(read_row(client, *servos), 7);

  // mbpoll with the row's own arguments: its -r counts from 1, the row's address from 0.
  if (!std::filesystem::exists("/usr/bin/mbpoll")) GTEST_SKIP() << "mbpoll is not installed";
  const auto* row = find_row(rows, "1", "holding", "max_angle_limit");
  ASSERT_NE(row, nullptr);
  std::vector<std::string> argv{"/usr/bin/mbpoll", "-1", "-p", std::to_string(plant.port())};
  std::istringstream words(row->at("mbpoll"));
  for (std::string word; words >> word;) argv.push_back(word);
  argv.push_back("127.0.0.1");
  const Finished mbpoll = run(argv, 20s);
  ASSERT_EQ(mbpoll.status, 0) << mbpoll.output;
  const std::string expected =
      "[" + row->at("address_1based") + "]: \t" + std::to_string(plant.arm().field(1, "max_angle_limit"));
  EXPECT_NE(mbpoll.output.find(expected), std::string::npos) << expected << "\n" << mbpoll.output;
}

TEST(Tags, ABadFormatIsAUsageErrorNamingTheFormats) {
  TempDir dir;
  std::ofstream(dir.file("gateway.yaml")) << "buses: []\n";
  const Finished bad = run({bin("sms-gateway"), "tags", "--config", dir.file("gateway.yaml"), "--format", "xml"});
  EXPECT_EQ(bad.status, 2) << bad.output;
  EXPECT_NE(bad.output.find("csv, node-red or fuxa"), std::string::npos) << bad.output;
}

TEST(Tags, AMissingConfigurationNamesTheFile) {
  TempDir dir;
  const std::string missing = dir.file("nowhere.yaml");
  const Finished bad = run({bin("sms-gateway"), "tags", "--config", missing, "--format", "csv"});
  EXPECT_EQ(bad.status, 2) << bad.output;
  EXPECT_NE(bad.output.find(missing), std::string::npos) << bad.output;
}

}  // namespace
}  // namespace sms::e2e
