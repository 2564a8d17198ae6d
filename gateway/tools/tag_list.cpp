#include "gateway/tools/tag_list.h"

#include <algorithm>
#include <charconv>
#include <stdexcept>
#include <utility>

#include "gateway/units/gateway_unit.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/field_unit.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"

namespace sms::gateway {

using modbus_map::BusRange;
using modbus_map::RegisterEntry;
using modbus_map::RegisterMap;
using nlohmann::json;

std::string_view to_string(TagSpace space) {
  switch (space) {
    case TagSpace::Holding: return "holding";
    case TagSpace::Input: return "input";
    case TagSpace::Coil: return "coil";
    case TagSpace::Discrete: return "discrete";
  }
  return "";
}

std::uint8_t read_function(const Tag& tag) {
  if (!tag.readable) return 0;
  switch (tag.space) {
    case TagSpace::Coil: return 1;
    case TagSpace::Discrete: return 2;
    case TagSpace::Holding: return 3;
    case TagSpace::Input: return 4;
  }
  return 0;
}

std::string write_functions(const Tag& tag) {
  if (!tag.writable) return "";
  if (tag.space == TagSpace::Coil) return "5 15";
  return tag.words == 1 ? "6 16" : "16";  // FC06 cannot write both words of a 32-bit value
}

std::string data_type(const Tag& tag) {
  if (tag.space == TagSpace::Coil || tag.space == TagSpace::Discrete) return "bool";
  if (tag.words == 2) return tag.is_signed ? "int32" : "uint32";
  return tag.is_signed ? "int16" : "uint16";
}

std::string access_text(const Tag& tag) { return std::string(tag.readable ? "R" : "") + (tag.writable ? "W" : ""); }

std::uint32_t address_1based(const Tag& tag) { return std::uint32_t{tag.address} + 1; }

std::string mbpoll_arguments(const Tag& tag) {
  // mbpoll's -t: 0 coils, 1 discrete inputs, 3 input registers, 4 holding registers; ":int"
  // reads 32 bits, -B takes the high word first.
  std::string type;
  switch (tag.space) {
    case TagSpace::Coil: type = "0"; break;
    case TagSpace::Discrete: type = "1"; break;
    case TagSpace::Input: type = "3"; break;
    case TagSpace::Holding: type = "4"; break;
  }
  if (tag.words == 2) type += ":int -B";
  return "-a " + std::to_string(tag.unit) + " -t " + type + " -r " + std::to_string(address_1based(tag));
}

std::string servo_label(const config::ServoConfig& servo, const std::string& bus) {
  if (!servo.name.empty()) return servo.name;
  return "bus " + bus + " id " + std::to_string(servo.servo_id);
}

namespace {

std::string joined_notes(std::string_view first, std::string_view second) {
  std::string text(first);
  if (!second.empty()) text += (text.empty() ? "" : "; ") + std::string(second);
  return text;
}

}  // namespace

std::vector<Tag> servo_unit_tags(const CatalogUnit& unit, BusRange poll_block, const std::string& bus) {
  const RegisterMap& map = unit.map;
  const config::ServoConfig& servo = *unit.servo;
  const std::string label = servo_label(servo, bus);
  std::vector<Tag> tags;
  const auto add = [&](const RegisterEntry& entry, TagSpace space, bool readable, bool writable,
                       std::string_view where) {
    const modbus_map::FieldUnit field_unit = modbus_map::field_unit(*entry.shown);
    const std::string_view notes = entry.link != nullptr ? entry.link->notes : entry.shown->notes;
    tags.push_back(Tag{.unit = servo.unit_id,
                       .servo = label,
                       .name = std::string(entry.shown->name),
                       .space = space,
                       .address = entry.address,
                       .words = 1,
                       .is_signed = entry.shown->encoding.kind != modbus_map::EncodingKind::Unsigned,
                       .readable = readable,
                       .writable = writable,
                       .scale = field_unit.scale,
                       .symbol = std::string(field_unit.symbol),
                       .notes = joined_notes(where, notes)});
  };
  // Each space asks the map itself whether it serves the field there.
  for (const RegisterEntry& entry : map.entries()) {
    if (entry.counterpart == nullptr) continue;  // 0x02 alone: no tag to poll
    const bool writable = entry.writable && !servo.read_only;
    const bool live = entry.readable && map.plan_holding_read(entry.address, 1).has_value();
    if (live || writable) add(entry, TagSpace::Holding, live, writable, live ? "live read" : "");
    if (entry.readable && map.plan_input_read(entry.address, 1, poll_block)) {
      add(entry, TagSpace::Input, true, false, "poll cache");
    }
    if (entry.shown->bit_space == modbus_map::BitSpace::Coil && map.plan_coil_read(entry.address, 1)) {
      add(entry, TagSpace::Coil, true, writable, "live read");
    }
    if (entry.shown->bit_space == modbus_map::BitSpace::DiscreteInput &&
        map.plan_discrete_read(entry.address, 1, poll_block)) {
      add(entry, TagSpace::Discrete, true, false, "");
    }
  }

  namespace facts = servo_facts_layout;
  struct Fact {
    std::string_view name;
    std::size_t offset;
    std::uint8_t words;
    std::string_view unit;
    std::string_view notes;
  };
  static constexpr Fact kFacts[] = {
      {"fact.status", facts::kStatus, 1, "", "status byte of the servo's last answer"},
      {"fact.online", facts::kOnline, 1, "", "1 online, 0 offline"},
      {"fact.cache_age", facts::kCacheAge, 1, "ms", "age of the poll cache; 65535 never polled or older"},
      {"fact.identity", facts::kIdentity, 1, "", "model (else firmware) read at discovery"},
      {"fact.replies_ok", facts::kRepliesOk, 2, "", "32-bit, wraps"},
      {"fact.timeouts", facts::kTimeouts, 2, "", "32-bit, wraps"},
      {"fact.offline_reason", facts::kOfflineReason, 1, "", "0 online, 1 no answer, 2 answers late (probed only)"},
  };
  for (const Fact& fact : kFacts) {
    tags.push_back(Tag{.unit = servo.unit_id,
                       .servo = label,
                       .name = std::string(fact.name),
                       .space = TagSpace::Input,
                       .address = static_cast<std::uint16_t>(facts::kFirstRegister + fact.offset),
                       .words = fact.words,
                       .readable = true,
                       .symbol = std::string(fact.unit),
                       .notes = "gateway fact; " + std::string(fact.notes)});
  }
  tags.push_back(Tag{.unit = servo.unit_id,
                     .servo = label,
                     .name = "fact.online",
                     .space = TagSpace::Discrete,
                     .address = facts::kOnlineBit,
                     .readable = true,
                     .symbol = {},
                     .notes = "gateway fact; 1 online"});
  return tags;
}

namespace {

// The gateway unit (docs/PLC_GUIDE.md "The gateway unit"): its map is code, not a table, so the
// addresses come from the constants it is served with.
void gateway_unit_tags(const config::Config& config, const UnitCatalog& catalog, std::vector<Tag>& tags) {
  namespace layout = gateway_unit_layout;
  const std::uint8_t unit = catalog.gateway_unit_id();
  const auto add = [&](std::string name, TagSpace space, std::uint16_t address, std::uint8_t words, bool writable,
                       std::string unit_symbol, std::string notes, double scale = 1.0) {
    tags.push_back(Tag{.unit = unit,
                       .servo = "gateway",
                       .name = std::move(name),
                       .space = space,
                       .address = address,
                       .words = words,
                       .readable = true,
                       .writable = writable,
                       .scale = scale,
                       .symbol = std::move(unit_symbol),
                       .notes = std::move(notes)});
  };
  const auto in = [&](std::string name, std::uint16_t address, std::uint8_t words, std::string unit_symbol,
                      std::string notes, double scale = 1.0) {
    add(std::move(name), TagSpace::Input, address, words, false, std::move(unit_symbol), std::move(notes), scale);
  };
  in("version_major", layout::kVersion, 1, "", "");
  in("version_minor", layout::kVersion + 1, 1, "", "");
  in("version_patch", layout::kVersion + 2, 1, "", "");
  in("uptime", layout::kUptime, 2, "s", "");
  in("bus_count", layout::kBusCount, 1, "", "");
  in("servo_count", layout::kServoCount, 1, "", "");
  in("estop_latched", layout::kEStopLatched, 1, "", "1 latched");
  in("estop_count", layout::kEStopCount, 2, "", "e-stops so far");
  in("owed_stops", layout::kOwedStops, 1, "", "servos owed a safe stop, every bus");
  in("failed_stops", layout::kFailedStops, 2, "", "safe stops that failed, every bus");
  in("late_servos", layout::kLateServos, 1, "", "servos offline because they answer late (probed only), every bus");
  for (std::size_t n = 0; n < config.buses.size(); ++n) {
    const auto block = static_cast<std::uint16_t>(layout::kFirstBusBlock + layout::kBusBlockSize * n);
    const std::string bus = "bus." + config.buses[n].name + ".";
    const std::uint16_t wd = block + layout::kWatchdogState;
    in(bus + "state", block + 0, 1, "", "0 down, 1 up");
    in(bus + "baud", block + 1, 1, "bit/s", "baud / 100", 100.0);
    in(bus + "poll_cycle", block + 2, 1, "µs", "last poll cycle, saturating");
    in(bus + "servos_online", block + 3, 1, "", "");
    in(bus + "frames_ok", block + 4, 2, "", "32-bit, wraps");
    in(bus + "timeouts", block + 6, 2, "", "32-bit, wraps");
    in(bus + "checksum_errors", block + 8, 2, "", "checksum and framing errors; 32-bit, wraps");
    in(bus + "watchdog_state", wd, 1, "", "0 off, 1 armed, 2 running, 3 tripped");
    in(bus + "watchdog_since_feed", wd + 1, 1, "ms", "65535: never, or longer");
    in(bus + "watchdog_trips", wd + 2, 2, "", "32-bit");
    in(bus + "watchdog_timeout", wd + 4, 1, "ms", "");
    in(bus + "last_stop_cause", wd + 5, 1, "", "0 none, 1 watchdog, 2 e-stop, 3 on_start, 4 on_stop, 5 commissioning");
    in(bus + "last_stop_latency", wd + 6, 2, "µs", "0 after a stop that failed");
    in(bus + "motion_blocked", wd + 8, 1, "", "1 while motion writes are refused");
    in(bus + "owed_stops", wd + 9, 1, "", "servos of the bus owed a safe stop");
    add(bus + "heartbeat", TagSpace::Holding, static_cast<std::uint16_t>(config::kHeartbeatRegisterBase + n), 1, true,
        "", "watchdog heartbeat (feed: heartbeat_register counts a changed value)");
  }
  add("action", TagSpace::Coil, layout::kActionCoil, 1, true, "",
      "write 1: ACTION on every packet bus (staged writes)");
  add("estop", TagSpace::Coil, layout::kEStopCoil, 1, true, "",
      "write 1 latches the e-stop and stops every bus, 0 resets");
  add("watchdog_rearm", TagSpace::Coil, layout::kWatchdogCoil, 1, true, "",
      "reads 1 while a watchdog is tripped; write 0 re-arms every tripped watchdog");
  static constexpr std::string_view kDiscrete[] = {"estop_latched", "watchdog_tripped", "motion_blocked",
                                                   "safe_stop_owed", "state_not_persisted"};
  static_assert(std::size(kDiscrete) == layout::kDiscreteInputCount);
  for (std::size_t i = 0; i < std::size(kDiscrete); ++i) {
    tags.push_back(Tag{.unit = unit,
                       .servo = "gateway",
                       .name = std::string(kDiscrete[i]),
                       .space = TagSpace::Discrete,
                       .address = static_cast<std::uint16_t>(i),
                       .readable = true,
                       .symbol = {},
                       .notes = {}});
  }
  for (std::size_t g = 0; g < config.sync_groups.size(); ++g) {
    const config::SyncGroupConfig& group = config.sync_groups[g];
    const std::string prefix = "sync." + group.name + ".";
    if (group.move_time) {
      add(prefix + "move_time", TagSpace::Holding,
          static_cast<std::uint16_t>(group.holding_register_start + group.members.size()), 1, true, "ms",
          "the timed move's time, written with the goals in one FC16 (0: each axis at its own speed)");
    }
    // The group's timed moves (docs/PLC_GUIDE.md "Timed group moves"): 2000 + 10·g.
    using Reg = layout::GroupRegister;
    const auto status = [&](const std::string& name, Reg reg, std::string unit_symbol, std::string notes) {
      in(prefix + name,
         static_cast<std::uint16_t>(layout::kFirstGroupBlock + layout::kGroupBlockSize * g +
                                    static_cast<std::uint16_t>(reg)),
         1, std::move(unit_symbol), std::move(notes));
    };
    status("moving", Reg::Moving, "", "1 while a timed move runs");
    status("time_left", Reg::TimeLeft, "ms", "");
    status("distance_to_go", Reg::DistanceToGo, "", "the largest of the members', position units");
    status("last_move", Reg::LastMove, "", "0 none, 1 as asked, 2 stretched, 3 refused");
    status("limiting_unit", Reg::LimitingUnit, "", "the unit that limits it");
    status("shortest_time", Reg::ShortestTime, "ms", "that unit's shortest time");
    status("move_time_used", Reg::MoveTime, "ms", "");
    for (std::size_t i = 0; i < group.members.size(); ++i) {
      const CatalogUnit* member = catalog.servo(group.members[i]);
      if (member == nullptr) continue;  // the loader refuses such groups
      const RegisterMap& native = member->native_map();
      const modbus_map::FieldSpec* field = modbus_map::field_by_name(native.servo_table(), group.field);
      if (field == nullptr) continue;
      const modbus_map::FieldUnit field_unit = modbus_map::field_unit(*field);
      tags.push_back(Tag{.unit = unit,
                         .servo = "gateway",
                         .name = prefix + "unit" + std::to_string(group.members[i]),
                         .space = TagSpace::Holding,
                         .address = static_cast<std::uint16_t>(group.holding_register_start + i),
                         .is_signed = field->encoding.kind != modbus_map::EncodingKind::Unsigned,
                         .readable = true,
                         .writable = !member->servo->read_only,
                         .scale = field_unit.scale,
                         .symbol = std::string(field_unit.symbol),
                         .notes = "sync group " + group.name + ": " + group.field + " of unit " +
                                  std::to_string(group.members[i]) +
                                  "; one FC16 over the group is one SYNC WRITE per bus"});
    }
  }
}

}  // namespace

std::vector<Tag> tag_list(const config::Config& config, const UnitCatalog& catalog) {
  std::vector<Tag> tags;
  for (unsigned id = 0; id < 256; ++id) {
    const CatalogUnit* unit = catalog.servo(static_cast<std::uint8_t>(id));
    if (unit == nullptr) continue;
    const config::BusConfig& bus = config.buses.at(unit->servo->bus_index);
    const auto block = poll_block_of(bus, *unit->servo);
    if (!block) throw std::runtime_error(block.error());
    auto unit_tags = servo_unit_tags(*unit, *block, bus.name);
    tags.insert(tags.end(), unit_tags.begin(), unit_tags.end());
  }
  gateway_unit_tags(config, catalog, tags);
  return tags;
}

std::string number_text(double value) {
  char buffer[32];
  const auto [end, error] = std::to_chars(buffer, buffer + sizeof buffer, value);
  return error == std::errc{} ? std::string(buffer, end) : std::string("1");
}

namespace {

// RFC 4180: fields with a comma, quote or line break are quoted, quotes doubled.
std::string csv_field(std::string_view text) {
  if (text.find_first_of(",\"\r\n") == std::string_view::npos) return std::string(text);
  std::string quoted = "\"";
  for (const char c : text) {
    if (c == '"') quoted += '"';
    quoted += c;
  }
  return quoted + '"';
}

}  // namespace

std::string tags_csv(const std::vector<Tag>& tags) {
  std::string out =
      "unit,servo,name,space,read_fc,write_fc,address,address_1based,mbpoll,data_type,scale,eng_unit,access,notes\r\n";
  for (const Tag& tag : tags) {
    const std::uint8_t read_fc = read_function(tag);
    const std::string fields[] = {std::to_string(tag.unit),
                                  tag.servo,
                                  tag.name,
                                  std::string(to_string(tag.space)),
                                  read_fc == 0 ? std::string() : std::to_string(read_fc),
                                  write_functions(tag),
                                  std::to_string(tag.address),
                                  std::to_string(address_1based(tag)),
                                  mbpoll_arguments(tag),
                                  data_type(tag),
                                  number_text(tag.scale),
                                  tag.symbol,
                                  access_text(tag),
                                  tag.notes};
    bool first = true;
    for (const std::string& field : fields) {
      if (!first) out += ',';
      out += csv_field(field);
      first = false;
    }
    out += "\r\n";
  }
  return out;
}

}  // namespace sms::gateway
