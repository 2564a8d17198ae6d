// `sms-gateway tags` (gateway/tools/tag_list.h): every row checked against the register map's own
// answer for its field (not against a list typed here), for every table and both profiles; the
// Node-RED flow and the FUXA devices parsed back and checked for the shapes those tools need.
#include "gateway/tools/tag_list.h"

#include <gtest/gtest.h>

#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "config/load.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/field_unit.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"

namespace sms::gateway {
namespace {

using modbus_map::RegisterEntry;
using nlohmann::json;

// Every table and both profiles: sts, sms1, scs on feetech, d55d, smsmb on modbus-rtu; a poll
// field selection on the d55d bus, a read-only view, a watchdog and two sync groups.
constexpr const char* kConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000,
     watchdog: {timeout_ms: 500, feed: heartbeat_register}}
  - {name: base, device: /dev/ttyUSB1, protocol: d55d, baud: 115200,
     poll_fields: [present_position, present_speed]}
  - {name: rtu, device: /dev/ttyUSB2, protocol: modbus-rtu, baud: 115200, watchdog: {timeout_ms: 500}}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts, name: shoulder}
  - {unit: 2, bus: arm, id: 2, table: sts, profile: smsmb}
  - {unit: 3, bus: arm, id: 3, table: sms1}
  - {unit: 4, bus: arm, id: 4, table: sms1, profile: smsmb}
  - {unit: 5, bus: arm, id: 5, table: scs}
  - {unit: 6, bus: arm, id: 1, table: sts, read_only: true, name: "shoulder, view"}
  - {unit: 11, bus: base, id: 1, table: d55d}
  - {unit: 21, bus: rtu, id: 1, table: smsmb}
sync_groups:
  - {name: arm_goals, field: goal_position, members: [1, 3], holding_register_start: 0, move_time: true}
  - {name: base_speeds, field: run_speed, members: [11], holding_register_start: 10}
)";

config::Config test_config() {
  auto config = config::load_config_string(kConfig, "<tag list test>");
  if (!config) throw std::runtime_error(config.error().to_string());
  return std::move(*config);
}

// RFC 4180 rows: quoted fields may hold commas, doubled quotes and line breaks.
std::vector<std::vector<std::string>> parse_csv(const std::string& text) {
  std::vector<std::vector<std::string>> rows(1);
  std::string field;
  bool quoted = false;
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (quoted) {
      if (c == '"' && i + 1 < text.size() && text[i + 1] == '"') {
        field += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        field += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      rows.back().push_back(std::move(field));
      field.clear();
    } else if (c == '\r' && i + 1 < text.size() && text[i + 1] == '\n') {
      rows.back().push_back(std::move(field));
      field.clear();
      rows.emplace_back();
      ++i;
    } else {
      field += c;
    }
  }
  if (rows.back().empty()) rows.pop_back();
  return rows;
}

using Row = std::map<std::string, std::string>;

std::vector<Row> csv_rows(const std::string& text) {
  const auto rows = parse_csv(text);
  std::vector<Row> out;
  for (std::size_t r = 1; r < rows.size(); ++r) {
    EXPECT_EQ(rows[r].size(), rows[0].size()) << "row " << r;
    Row row;
    for (std::size_t c = 0; c < rows[0].size() && c < rows[r].size(); ++c) row[rows[0][c]] = rows[r][c];
    out.push_back(std::move(row));
  }
  return out;
}

class TagListTest : public ::testing::Test {
 protected:
  config::Config config_ = test_config();
  UnitCatalog catalog_{config_};
  std::vector<Tag> tags_ = tag_list(config_, catalog_);
  std::vector<Row> rows_ = csv_rows(tags_csv(tags_));

  modbus_map::BusRange poll_block(int unit) const {
    const config::ServoConfig& servo = *catalog_.servo(static_cast<std::uint8_t>(unit))->servo;
    return *poll_block_of(config_.buses[servo.bus_index], servo);
  }
};

TEST_F(TagListTest, HeaderNamesTheColumns) {
  const auto rows = parse_csv(tags_csv(tags_));
  ASSERT_FALSE(rows.empty());
  EXPECT_EQ(rows[0], (std::vector<std::string>{"unit", "servo", "name", "space", "read_fc", "write_fc", "address",
                                               "address_1based", "mbpoll", "data_type", "scale", "eng_unit", "access",
                                               "notes"}));
  EXPECT_EQ(rows.size(), tags_.size() + 1);
}

// Each servo row agrees with what RegisterMap answers for its field and space.
TEST_F(TagListTest, EveryServoRowAgreesWithTheRegisterMap) {
  std::set<int> units_seen;
  for (const Row& row : rows_) {
    const int unit = std::stoi(row.at("unit"));
    const CatalogUnit* servo = catalog_.servo(static_cast<std::uint8_t>(unit));
    if (servo == nullptr || row.at("name").starts_with("fact.")) continue;
    units_seen.insert(unit);
    const auto& map = servo->map;
    const auto address = static_cast<std::uint16_t>(std::stoi(row.at("address")));
    SCOPED_TRACE("unit " + row.at("unit") + " " + row.at("space") + " " + row.at("address") + " " + row.at("name"));
    const RegisterEntry* entry = map.entry_at(address);
    ASSERT_NE(entry, nullptr);
    EXPECT_EQ(row.at("name"), entry->shown->name);
    EXPECT_EQ(std::stoi(row.at("address_1based")), address + 1);
    const bool writable = entry->writable && !servo->servo->read_only;
    const std::string space = row.at("space");
    const std::string access = row.at("access");
    if (space == "holding") {
      const auto plan = map.plan_holding_read(address, 1);
      EXPECT_EQ(row.at("read_fc") == "3", plan.has_value() && !plan->reads.empty());
      EXPECT_EQ(row.at("write_fc"), writable ? "6 16" : "");
      EXPECT_EQ(row.at("mbpoll"), "-a " + row.at("unit") + " -t 4 -r " + row.at("address_1based"));
      if (writable) {  // a write of the field's own minimum passes the map's value check, or is refused as a value
        const auto check = map.check_write(*entry, entry->min);
        EXPECT_TRUE(check || check.error().code == modbus_map::ModbusException::IllegalDataValue);
      }
    } else if (space == "input") {
      EXPECT_TRUE(map.plan_input_read(address, 1, poll_block(unit)).has_value());
      EXPECT_EQ(row.at("read_fc"), "4");
      EXPECT_EQ(row.at("write_fc"), "");
      EXPECT_EQ(access, "R");
      EXPECT_EQ(row.at("mbpoll"), "-a " + row.at("unit") + " -t 3 -r " + row.at("address_1based"));
    } else if (space == "coil") {
      EXPECT_TRUE(map.plan_coil_read(address, 1).has_value());
      EXPECT_EQ(row.at("read_fc"), "1");
      EXPECT_EQ(row.at("write_fc"), writable ? "5 15" : "");
      EXPECT_EQ(row.at("data_type"), "bool");
    } else if (space == "discrete") {
      EXPECT_TRUE(map.plan_discrete_read(address, 1, poll_block(unit)).has_value());
      EXPECT_EQ(row.at("read_fc"), "2");
      EXPECT_EQ(row.at("data_type"), "bool");
    } else {
      ADD_FAILURE() << "space " << space;
    }
    if (space == "holding" || space == "input") {
      const bool is_signed = entry->shown->encoding.kind != modbus_map::EncodingKind::Unsigned;
      EXPECT_EQ(row.at("data_type"), is_signed ? "int16" : "uint16");
      EXPECT_EQ(std::stod(row.at("scale")), modbus_map::field_unit(*entry->shown).scale);
      EXPECT_EQ(row.at("eng_unit"), modbus_map::field_unit(*entry->shown).symbol);
    }
    EXPECT_EQ(access, std::string(row.at("read_fc").empty() ? "" : "R") + (row.at("write_fc").empty() ? "" : "W"));
  }
  EXPECT_EQ(units_seen, (std::set<int>{1, 2, 3, 4, 5, 6, 11, 21}));
}

// The other way round: every field the map serves has its rows.
TEST_F(TagListTest, EveryFieldOfEveryMapIsListedInEachSpaceItServes) {
  std::set<std::string> listed;
  for (const Tag& tag : tags_) {
    listed.insert(std::to_string(tag.unit) + " " + std::string(to_string(tag.space)) + " " +
                  std::to_string(tag.address));
  }
  for (const int unit : {1, 2, 3, 4, 5, 6, 11, 21}) {
    const CatalogUnit* servo = catalog_.servo(static_cast<std::uint8_t>(unit));
    for (const RegisterEntry& entry : servo->map.entries()) {
      if (entry.counterpart == nullptr) continue;
      const std::string key = std::to_string(unit) + " ";
      const std::string at = " " + std::to_string(entry.address);
      if (entry.readable || (entry.writable && !servo->servo->read_only)) {
        EXPECT_TRUE(listed.contains(key + "holding" + at)) << key << entry.shown->name;
      }
      if (servo->map.plan_input_read(entry.address, 1, poll_block(unit))) {
        EXPECT_TRUE(listed.contains(key + "input" + at)) << key << entry.shown->name;
      }
      if (entry.shown->bit_space == modbus_map::BitSpace::Coil) {
        EXPECT_TRUE(listed.contains(key + "coil" + at)) << key << entry.shown->name;
      }
    }
  }
}

TEST_F(TagListTest, ReadOnlyViewHasNoWrites) {
  for (const Tag& tag : tags_) {
    if (tag.unit == 6) {
      EXPECT_FALSE(tag.writable) << tag.name;
    }
  }
}

TEST_F(TagListTest, GatewayUnitListsSafetyHeartbeatsAndSyncGroups) {
  std::map<std::string, const Tag*> gateway;
  for (const Tag& tag : tags_) {
    if (tag.unit == 255) gateway[std::string(to_string(tag.space)) + " " + tag.name] = &tag;
  }
  ASSERT_TRUE(gateway.contains("coil estop"));
  EXPECT_EQ(gateway["coil estop"]->address, 1);
  ASSERT_TRUE(gateway.contains("coil watchdog_rearm"));
  EXPECT_EQ(gateway["coil watchdog_rearm"]->address, 2);
  ASSERT_TRUE(gateway.contains("holding bus.rtu.heartbeat"));
  EXPECT_EQ(gateway["holding bus.rtu.heartbeat"]->address, 1002);
  ASSERT_TRUE(gateway.contains("input bus.base.watchdog_state"));
  EXPECT_EQ(gateway["input bus.base.watchdog_state"]->address, 100 + 20 + 10);
  ASSERT_TRUE(gateway.contains("holding sync.arm_goals.unit3"));
  EXPECT_EQ(gateway["holding sync.arm_goals.unit3"]->address, 1);
  ASSERT_TRUE(gateway.contains("holding sync.base_speeds.unit11"));
  EXPECT_EQ(gateway["holding sync.base_speeds.unit11"]->address, 10);
  EXPECT_EQ(gateway.count("discrete estop_latched"), 1U);
  // The timed move's time after the goals, and each group's status block at 2000 + 10·g.
  ASSERT_TRUE(gateway.contains("holding sync.arm_goals.move_time"));
  EXPECT_EQ(gateway["holding sync.arm_goals.move_time"]->address, 2);
  EXPECT_TRUE(gateway["holding sync.arm_goals.move_time"]->writable);
  EXPECT_EQ(gateway["holding sync.arm_goals.move_time"]->symbol, "ms");
  EXPECT_FALSE(gateway.contains("holding sync.base_speeds.move_time"));
  ASSERT_TRUE(gateway.contains("input sync.arm_goals.moving"));
  EXPECT_EQ(gateway["input sync.arm_goals.moving"]->address, 2000);
  ASSERT_TRUE(gateway.contains("input sync.base_speeds.last_move"));
  EXPECT_EQ(gateway["input sync.base_speeds.last_move"]->address, 2013);
  ASSERT_TRUE(gateway.contains("input sync.base_speeds.move_time_used"));
  EXPECT_EQ(gateway["input sync.base_speeds.move_time_used"]->address, 2016);
}

TEST_F(TagListTest, CsvQuotesPerRfc4180) {
  const std::string csv = tags_csv(tags_);
  EXPECT_NE(csv.find("\"shoulder, view\""), std::string::npos);
  bool view_parsed = false;
  for (const Row& row : rows_) view_parsed = view_parsed || row.at("servo") == "shoulder, view";
  EXPECT_TRUE(view_parsed);
}

const json& node_of(const json& flow, const json& id) {
  for (const json& node : flow) {
    if (node["id"] == id) return node;
  }
  static const json none = json::object({{"type", "none"}, {"wires", json::array({json::array({""})})}});
  ADD_FAILURE() << "no node " << id;
  return none;
}

TEST_F(TagListTest, NodeRedFlowIsWiredAndShowsErrors) {
  const json flow = json::parse(node_red_flow(config_, catalog_, FlowTarget{"10.0.0.5", 1502}).dump());
  int heartbeats = 0;
  std::map<int, int> servo_writes;
  ASSERT_TRUE(flow.is_array());
  std::set<std::string> ids;
  std::string tab;
  std::string client;
  for (const json& node : flow) {
    ASSERT_TRUE(node.contains("id") && node.contains("type")) << node.dump();
    EXPECT_TRUE(ids.insert(node["id"].get<std::string>()).second) << "duplicate id " << node["id"];
    if (node["type"] == "tab") tab = node["id"];
    if (node["type"] == "modbus-client") client = node["id"];
  }
  ASSERT_FALSE(tab.empty());
  ASSERT_FALSE(client.empty());
  std::map<std::string, int> counts;
  for (const json& node : flow) {
    const std::string type = node["type"];
    ++counts[type];
    if (type == "tab") continue;
    if (type == "modbus-client") {
      // Every property of node-red-contrib-modbus's modbus-client defaults (src/modbus-client.html).
      for (const char* key : {"name",
                              "clienttype",
                              "bufferCommands",
                              "stateLogEnabled",
                              "queueLogEnabled",
                              "failureLogEnabled",
                              "tcpHost",
                              "tcpPort",
                              "tcpType",
                              "serialPort",
                              "serialType",
                              "serialBaudrate",
                              "serialDatabits",
                              "serialStopbits",
                              "serialParity",
                              "serialConnectionDelay",
                              "serialAsciiResponseStartDelimiter",
                              "unit_id",
                              "commandDelay",
                              "clientTimeout",
                              "reconnectOnTimeout",
                              "reconnectTimeout",
                              "parallelUnitIdsAllowed",
                              "showErrors",
                              "showWarnings",
                              "showLogs"}) {
        EXPECT_TRUE(node.contains(key)) << key;
      }
      EXPECT_EQ(node["tcpHost"], "10.0.0.5");
      EXPECT_EQ(node["tcpPort"], "1502");
      EXPECT_EQ(node["clienttype"], "tcp");
      continue;
    }
    EXPECT_EQ(node["z"], tab) << node.dump();
    ASSERT_TRUE(node["wires"].is_array()) << node.dump();
    for (const json& output : node["wires"]) {
      for (const json& target : output) EXPECT_TRUE(ids.contains(target.get<std::string>())) << node.dump();
    }
    if (type == "modbus-read" || type == "modbus-write") {
      EXPECT_EQ(node["server"], client);
      EXPECT_EQ(node["showErrors"], true) << node.dump();
      EXPECT_EQ(node["wires"].size(), 2U);  // both nodes have two outputs
      for (const char* key : {"name", "showStatusActivities", "showWarnings", "unitid", "dataType", "adr", "quantity",
                              "delayOnStart", "startDelayTime", "emptyMsgOnFail"}) {
        EXPECT_TRUE(node.contains(key)) << key << " " << node.dump();
      }
    }
    if (type == "inject") {  // Node-RED's inject defaults
      for (const char* key :
           {"name", "props", "repeat", "crontab", "once", "onceDelay", "topic", "payload", "payloadType"}) {
        EXPECT_TRUE(node.contains(key)) << key;
      }
      ASSERT_EQ(node["wires"].size(), 1U);
      ASSERT_EQ(node["wires"][0].size(), 1U);
      const json& next = node_of(flow, node["wires"][0][0]);
      if (node["name"].get<std::string>().starts_with("heartbeat")) {
        // The heartbeat of bus arm (fed by its heartbeat register): a changed value into holding
        // 1000 of the gateway unit, three times a timeout (500 ms).
        EXPECT_EQ(node["repeat"], "0.16666666666666666") << node.dump();
        EXPECT_EQ(node["once"], true);
        EXPECT_EQ(next["type"], "function");
        const json& write = node_of(flow, next["wires"][0][0]);
        EXPECT_EQ(write["type"], "modbus-write");
        EXPECT_EQ(write["unitid"], "255");
        EXPECT_EQ(write["dataType"], "HoldingRegister");
        EXPECT_EQ(write["adr"], "1000");
        ++heartbeats;
      } else {
        // It re-arms: false into a write of coil 2 of the gateway unit.
        EXPECT_EQ(node["payload"], "false");
        EXPECT_EQ(node["payloadType"], "bool");
        EXPECT_EQ(next["type"], "modbus-write");
        EXPECT_EQ(next["unitid"], "255");
        EXPECT_EQ(next["dataType"], "Coil");
        EXPECT_EQ(next["adr"], "2");
      }
    }
    if (type == "modbus-read") {
      EXPECT_EQ(node["dataType"], "InputRegister");
      const int unit = std::stoi(node["unitid"].get<std::string>());
      const CatalogUnit* servo = catalog_.servo(static_cast<std::uint8_t>(unit));
      ASSERT_NE(servo, nullptr);
      // The whole block is one FC04 the map accepts.
      EXPECT_TRUE(servo->map.plan_input_read(static_cast<std::uint16_t>(std::stoi(node["adr"].get<std::string>())),
                                             static_cast<std::uint16_t>(std::stoi(node["quantity"].get<std::string>())),
                                             poll_block(unit)))
          << node.dump();
      for (const char* key : {"topic", "logIOActivities", "rate", "rateUnit", "enableDeformedMessages", "useIOFile",
                              "ioFile", "useIOForPayload"}) {
        EXPECT_TRUE(node.contains(key)) << key;
      }
    }
    if (type == "modbus-read") {
      // Into a function node that names and scales the registers, then the debug node.
      const json& scaling = node_of(flow, node["wires"][0][0]);
      EXPECT_EQ(scaling["type"], "function");
      EXPECT_NE(scaling["func"].get<std::string>().find("\"name\":\"present_position\""), std::string::npos)
          << scaling["func"];
    }
    if (type == "modbus-write" && node["unitid"] != "255") {
      const int unit = std::stoi(node["unitid"].get<std::string>());
      const CatalogUnit* servo = catalog_.servo(static_cast<std::uint8_t>(unit));
      ASSERT_NE(servo, nullptr);
      const RegisterEntry* entry =
          servo->map.entry_at(static_cast<std::uint16_t>(std::stoi(node["adr"].get<std::string>())));
      ASSERT_NE(entry, nullptr);
      // What the servo needs written to move: its torque, speed and goal fields (modbus_map/motion.h).
      const auto& motion = modbus_map::motion_spec(servo->map.shown_table().id);
      EXPECT_TRUE(entry->shown->name == motion.goal_position || entry->shown->name == motion.goal_speed ||
                  entry->shown->name == motion.torque)
          << entry->shown->name;
      EXPECT_TRUE(entry->writable);
      ++servo_writes[unit];
    }
  }
  EXPECT_EQ(counts["modbus-client"], 1);
  EXPECT_EQ(counts["modbus-read"], 8);  // every servo unit
  EXPECT_EQ(counts["inject"], 3);       // arm and rtu have watchdogs; arm's is fed by its heartbeat register
  EXPECT_EQ(heartbeats, 1);
  EXPECT_EQ(counts["function"], 8 + 1);  // one scaling per read, the heartbeat's counter
  EXPECT_EQ(servo_writes.size(), 7U);    // the writable units
  // d55d (unit 11) is given its run speed too: it runs at 0 after power-on.
  EXPECT_EQ(servo_writes[11], 2);
}

TEST_F(TagListTest, FuxaTagsAgreeWithTheCsv) {
  const json devices = json::parse(fuxa_devices(tags_, FlowTarget{}).dump());
  ASSERT_TRUE(devices.is_array());
  std::set<std::string> csv_keys;
  for (const Row& row : rows_) {
    const std::map<std::string, std::string> memaddress{
        {"coil", "000000"}, {"discrete", "100000"}, {"input", "300000"}, {"holding", "400000"}};
    csv_keys.insert(row.at("unit") + " " + memaddress.at(row.at("space")) + " " + row.at("address_1based") + " " +
                    row.at("data_type"));
  }
  const std::map<std::string, std::string> types{
      {"Bool", "bool"}, {"Int16", "int16"}, {"UInt16", "uint16"}, {"UInt32", "uint32"}, {"Int32", "int32"}};
  std::size_t tag_count = 0;
  std::set<std::string> device_ids;
  for (const json& device : devices) {
    EXPECT_EQ(device["type"], "ModbusTCP");
    EXPECT_TRUE(device_ids.insert(device["id"].get<std::string>()).second);
    // FUXA's driver reads the port from the address only (modbus/index.js `_connect`).
    EXPECT_EQ(device["property"]["address"], "127.0.0.1:502");
    EXPECT_EQ(device["property"]["port"], "502");
    EXPECT_EQ(device["id"].get<std::string>().rfind("d_sms_127_0_0_1_502_unit", 0), 0u) << device["id"];
    const std::string unit = device["property"]["slaveid"];
    for (const auto& [id, tag] : device["tags"].items()) {
      ++tag_count;
      EXPECT_EQ(tag["id"], id);
      const std::string key = unit + " " + tag["memaddress"].get<std::string>() + " " +
                              tag["address"].get<std::string>() + " " + types.at(tag["type"].get<std::string>());
      EXPECT_TRUE(csv_keys.contains(key)) << key;
      EXPECT_GT(tag["divisor"].get<double>(), 0.0);
    }
  }
  // Every tag but the read-only holding registers the poll cache serves as input registers too:
  // FUXA polls those from the cache only.
  std::size_t polled_twice = 0;
  for (const Tag& tag : tags_) {
    if (tag.space != TagSpace::Holding || tag.writable) continue;
    polled_twice += std::any_of(tags_.begin(), tags_.end(), [&](const Tag& other) {
      return other.unit == tag.unit && other.space == TagSpace::Input && other.address == tag.address;
    });
  }
  EXPECT_GT(polled_twice, 0U);
  EXPECT_EQ(tag_count, rows_.size() - polled_twice);
}

// FUXA with the device's "options" set polls each run of adjacent tags with one request
// (server/runtime/devices/modbus: the fragmented reads). Every such request of a servo unit is
// one the gateway serves: the map accepts it, or it lies in the facts the router serves. A unit
// whose run would cross a multiple of 100 is split over two devices.
TEST_F(TagListTest, EveryFuxaPollRequestIsServed) {
  const json devices = fuxa_devices(tags_, FlowTarget{});
  for (const json& device : devices) {
    EXPECT_EQ(device["property"]["options"], true) << device["name"];
    const int unit = std::stoi(device["property"]["slaveid"].get<std::string>());
    const CatalogUnit* servo = catalog_.servo(static_cast<std::uint8_t>(unit));
    // FUXA's key: memory area + zero-based offset; a run goes on while the next tag starts
    // where the last one ended (or inside it).
    std::map<long, int> words;
    for (const auto& [id, tag] : device["tags"].items()) {
      const long key =
          std::stol(tag["memaddress"].get<std::string>()) + std::stol(tag["address"].get<std::string>()) - 1;
      words[key] = std::max(words[key], tag["type"] == "UInt32" || tag["type"] == "Int32" ? 2 : 1);
    }
    std::vector<std::pair<long, long>> runs;  // [start, end)
    for (const auto& [key, size] : words) {
      if (runs.empty() || key > runs.back().second) {
        runs.emplace_back(key, key + size);
      } else {
        runs.back().second = std::max(runs.back().second, key + size);
      }
    }
    for (const auto& [start, end] : runs) {
      const long area = start / 100000 * 100000;
      const auto address = static_cast<std::uint16_t>(start - area);
      const auto count = static_cast<std::uint16_t>(end - start);
      SCOPED_TRACE("unit " + std::to_string(unit) + " area " + std::to_string(area) + " " + std::to_string(address) +
                   " +" + std::to_string(count));
      // FUXA reads every tag of a run from the request it started in: a run must keep to one
      // block of 100 addresses (its TOKEN_LIMIT), or the tags past the boundary never update.
      EXPECT_EQ(address / 100, (address + count - 1) / 100);
      if (servo == nullptr) continue;  // the gateway unit: its spaces are code, not a map
      if (address >= servo_facts_layout::kFirstRegister) {
        EXPECT_LE(std::uint32_t{address} + count,
                  area == 300000 ? servo_facts_layout::kFirstRegister + servo_facts_layout::kRegisterCount
                                 : servo_facts_layout::kOnlineBit + 1U);
        continue;
      }
      const auto& map = servo->map;
      if (area == 400000) {
        EXPECT_TRUE(map.plan_holding_read(address, count).has_value());
      } else if (area == 300000) {
        EXPECT_TRUE(map.plan_input_read(address, count, poll_block(unit)).has_value());
      } else if (area == 0) {
        EXPECT_TRUE(map.plan_coil_read(address, count).has_value());
      } else {
        EXPECT_TRUE(map.plan_discrete_read(address, count, poll_block(unit)).has_value());
      }
    }
  }
}

}  // namespace
}  // namespace sms::gateway
