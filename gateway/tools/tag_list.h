#pragma once
// `sms-gateway tags`: every Modbus address a configuration serves, as tags for an HMI or SCADA
// (docs/HMI.md): a CSV table, a Node-RED flow (node-red-contrib-modbus), a FUXA device list.
// Servo units come from the same register maps the gateway maps requests with (UnitCatalog,
// RegisterMap), their input window from the same poll block; the gateway unit's registers from
// the constants the gateway unit serves them with.
//
//   const UnitCatalog catalog(config);
//   const auto tags = tag_list(config, catalog);
//   std::cout << tags_csv(tags);
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "config/config.h"
#include "gateway/service/unit_catalog.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

enum class TagSpace : std::uint8_t { Holding, Input, Coil, Discrete };
std::string_view to_string(TagSpace space);  // "holding", "input", "coil", "discrete"

struct Tag {
  std::uint8_t unit = 0;
  std::string servo;  // the unit's configured name, else "bus B id N"; "gateway" for the gateway unit
  std::string name;   // the field's name; gateway unit: "bus.<bus>.watchdog_state" etc.
  TagSpace space = TagSpace::Holding;
  std::uint16_t address = 0;  // zero-based, as on the wire
  std::uint8_t words = 1;     // 2: a 32-bit counter, high word first
  bool is_signed = false;     // registers: two's complement
  bool readable = false;
  bool writable = false;
  double scale = 1.0;  // engineering value = register value × scale
  std::string symbol;  // the engineering unit: "V", "°C", "steps"; may be empty
  std::string notes;
};

// What each tool needs of a tag, in its own terms.
std::uint8_t read_function(const Tag& tag);    // 1, 2, 3, 4; 0 when not readable
std::string write_functions(const Tag& tag);   // "6 16", "16", "5 15", or ""
std::string data_type(const Tag& tag);         // "bool", "uint16", "int16", "uint32"
std::string access_text(const Tag& tag);       // "R", "W", "RW"
std::string mbpoll_arguments(const Tag& tag);  // "-a 1 -t 4 -r 43" (mbpoll counts from 1)
std::uint32_t address_1based(const Tag& tag);  // address + 1, as FUXA and mbpoll count
std::string number_text(double value);         // shortest round-trip text: "0.1", "2048"
// A servo's name in the lists: its configured name, else "bus B id N".
std::string servo_label(const config::ServoConfig& servo, const std::string& bus);

// The tags of one servo unit: every field its map shows in each space that serves it (holding
// registers, the input registers of `poll_block`, coils, discrete inputs), then the facts the
// gateway keeps about the servo (input registers and discrete inputs 1000+). Fields without a
// counterpart (smsmb profile registers the servo does not have) are left out: they answer 0x02.
std::vector<Tag> servo_unit_tags(const CatalogUnit& unit, modbus_map::BusRange poll_block, const std::string& bus);
// Every unit of the configuration, ascending unit id, the gateway unit last. Throws
// std::runtime_error naming the bus when a poll block cannot be resolved.
std::vector<Tag> tag_list(const config::Config& config, const UnitCatalog& catalog);

// RFC 4180: a header row, then one row per tag; CRLF line ends. Columns: unit (the Modbus unit
// id), servo, name, space, read_fc, write_fc, address, address_1based, mbpoll, data_type, scale,
// eng_unit, access, notes.
std::string tags_csv(const std::vector<Tag>& tags);

struct FlowTarget {
  std::string host = "127.0.0.1";
  std::uint16_t port = 502;
};

// A Node-RED flow (an array of nodes) for node-red-contrib-modbus: one tab, one modbus-client,
// per servo unit a modbus-read of its input registers (its poll block) into a function node that
// names and scales them, and a modbus-write of each field it needs written to move (torque, speed,
// goal); per bus fed by its heartbeat register an inject + counter + modbus-write that feeds it;
// per bus with a watchdog an inject + modbus-write that re-arms the watchdogs,
// and a debug node everything answers to.
nlohmann::json node_red_flow(const config::Config& config, const UnitCatalog& catalog, const FlowTarget& target);

// FUXA devices (an array, as FUXA's Devices > Import reads it): one ModbusTCP device per unit,
// its tags keyed by id.
nlohmann::json fuxa_devices(const std::vector<Tag>& tags, const FlowTarget& target);

}  // namespace sms::gateway
