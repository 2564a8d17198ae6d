#include "gateway/tools/tool_servo.h"

#include <algorithm>
#include <array>
#include <optional>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "modbus_map/baud_tables.h"
#include "modbus_map/eeprom_lock.h"
#include "modbus_map/tables.h"
#include "protocol/modbus_pdu.h"

namespace sms::gateway {

using modbus_map::Access;
using modbus_map::Addressing;
using modbus_map::EepromUnlock;
using modbus_map::FieldSpec;
using modbus_map::TableId;
using modbus_map::TableSpec;

namespace {

// How each table calibrates its mid-point (docs/PROTOCOL.md §2.1 address 40, §2.4 fault reset bit 2).
struct MidpointCalibration {
  TableId table;
  std::string_view field;
  std::int32_t value;
  std::string_view what;
};
constexpr std::array<MidpointCalibration, 2> kCalibrations{{
    {TableId::Sts, "torque_enable", 128, "128 to torque_enable (address 40)"},
    {TableId::Smsmb, "fault_reset", 1 << 2, "fault_reset (0x86) bit 2, set centre"},
}};

// Packet tables read in chunks of at most this many bytes (one READ each).
constexpr std::uint16_t kDumpChunkBytes = 128;
constexpr std::uint16_t kMaxReadRegisters = protocol::modbus_limits::kReadRegisters;

modbus_map::ByteOrder order_of(const TableSpec& table) {
  return table.addressing == Addressing::Register ? modbus_map::ByteOrder::HighFirst : table.default_byte_order;
}

std::uint16_t span_of(const TableSpec& table, const FieldSpec& field) {
  return modbus_map::address_span(table.addressing, field);
}

// The servo's ID in messages: "servo 3", "every servo (broadcast)".
std::string who(const ToolTarget& target, const ToolProtocol& protocol) {
  if (target.id == protocol.broadcast_id) return "every servo (broadcast ID " + std::to_string(target.id) + ")";
  return "servo " + std::to_string(target.id);
}

const FieldSpec& require_field(const TableSpec& table, std::string_view name) {
  const FieldSpec* field = modbus_map::field_by_name(table, name);
  if (field == nullptr) {
    throw std::logic_error(fmt::format("table {} has no field {}", table.name, name));
  }
  return *field;
}

// Common checks of every tool: the table is spoken on this link, broadcast needs force.
Expected<Ok> check_target(const ServoLink& link, const ToolTarget& target, std::string_view action) {
  const auto& table = modbus_map::table(target.table);
  const auto protocol = link.settings().protocol;
  if (table.protocol != protocol) {
    return unexpected(fmt::format("table {} is spoken on {} buses, not {}: give --table {}", table.name,
                                  protocol::to_string(table.protocol), protocol::to_string(protocol),
                                  modbus_map::table(tool_protocol(protocol).default_table).name));
  }
  const ToolProtocol& rules = tool_protocol(protocol);
  if (target.id == rules.broadcast_id && !target.force) {
    return unexpected(fmt::format(
        "ID {} is the broadcast ID: {} would hit every servo on the bus at once, and none answers to confirm. "
        "Connect only the one servo and add --force if that is what you want",
        target.id, action));
  }
  if (target.id != rules.broadcast_id && (target.id < rules.first_id || target.id > rules.last_id)) {
    return unexpected(fmt::format("ID {} is not a servo ID on {} buses ({}-{})", target.id,
                                  protocol::to_string(protocol), rules.first_id, rules.last_id));
  }
  return Ok{};
}

Expected<std::int32_t> read_field(ServoLink& link, const TableSpec& table, std::uint8_t id, const FieldSpec& field) {
  const LinkAnswer answer = link.read(id, field.addr, span_of(table, field));
  if (!answer.ok()) {
    return unexpected(fmt::format("reading {} of servo {} failed: {}", field.name, id,
                                  answer.detail.empty() ? std::string(to_string(answer.status)) : answer.detail));
  }
  const std::uint32_t raw = modbus_map::load_raw(answer.data, field.size, order_of(table));
  return modbus_map::decode_value(field, raw);
}

Bytes field_bytes(const TableSpec& table, const FieldSpec& field, std::uint32_t raw) {
  Bytes bytes(field.size);
  modbus_map::store_raw(bytes, field.size, order_of(table), raw);
  return bytes;
}

// Writes a field. `tolerate_silence`: the change itself can keep the answer from arriving
// (a new ID answers under another ID, a new baud at another rate); success is then decided
// by the verification that follows, and only a refusal or a port error fails here.
Expected<Ok> write_field(ServoLink& link, const TableSpec& table, std::uint8_t id, const FieldSpec& field,
                         std::uint32_t raw, bool tolerate_silence = false) {
  const LinkAnswer answer = link.write(id, field.addr, field_bytes(table, field, raw));
  if (answer.ok()) return Ok{};
  if (tolerate_silence && (answer.status == LinkStatus::Timeout || answer.status == LinkStatus::Corrupt)) return Ok{};
  return unexpected(fmt::format("writing {} = {} to servo {} failed: {}", field.name, raw, id,
                                answer.detail.empty() ? std::string(to_string(answer.status)) : answer.detail));
}

// Whether anything answers on `id`: before an ID is given away a silence must be sure, so the
// check waits longer than a scan does (a late answer would mean two servos on one ID).
constexpr std::chrono::milliseconds kFreeIdExtraWait{20};

LinkAnswer ask_carefully(ServoLink& link, std::uint8_t id) {
  const auto latency = link.settings().latency;
  link.set_latency(latency + kFreeIdExtraWait);
  LinkAnswer answer = link.ping(id);
  link.set_latency(latency);
  return answer;
}

Expected<Ok> require_answer(ServoLink& link, std::uint8_t id, std::string_view hint) {
  const LinkAnswer answer = link.ping(id);
  if (answer.ok()) return Ok{};
  if (answer.status == LinkStatus::PortError) return unexpected(answer.detail);
  return unexpected(
      fmt::format("no servo answers on ID {} at {} bit/s ({}){}", id, link.settings().baud, answer.detail, hint));
}

// Opens the EEPROM lock when the table has one and it is closed (modbus_map/eeprom_lock.h); the
// lock as read, for relock(). A broadcast cannot read it: the table's default is assumed.
Expected<EepromUnlock> unlock(ServoLink& link, const TableSpec& table, std::uint8_t id, bool broadcast,
                              const Say& say) {
  EepromUnlock lock{modbus_map::eeprom_lock(table)};
  if (lock.field == nullptr) {
    say(fmt::format("table {} has no EEPROM lock: its EEPROM writes persist", table.name));
    return lock;
  }
  lock.read = lock.field->default_value.value_or(1);
  if (!broadcast) {
    auto current = read_field(link, table, id, *lock.field);
    if (!current) return unexpected(current.error());
    lock.read = *current;
  }
  if (!lock.needed()) {
    say(fmt::format("EEPROM lock ({} at {}) is already {}: writes persist", lock.field->name, lock.field->addr,
                    lock.read));
    return lock;
  }
  say(lock.unlock_text());
  if (auto written = write_field(link, table, id, *lock.field, static_cast<std::uint32_t>(modbus_map::kEepromUnlocked));
      !written) {
    return unexpected(written.error());
  }
  return lock;
}

// Puts the lock back as unlock() found it.
Expected<Ok> relock(ServoLink& link, const TableSpec& table, std::uint8_t id, const EepromUnlock& lock,
                    const Say& say) {
  if (!lock.needed()) return Ok{};
  say(lock.relock_text());
  return write_field(link, table, id, *lock.field, static_cast<std::uint32_t>(lock.read));
}

}  // namespace

Expected<std::string> set_servo_id(ServoLink& link, const ToolTarget& target, std::uint8_t new_id, const Say& say) {
  if (auto checked = check_target(link, target, "set-id"); !checked) return unexpected(checked.error());
  const TableSpec& table = modbus_map::table(target.table);
  const ToolProtocol& rules = tool_protocol(link.settings().protocol);
  const FieldSpec& id_field = require_field(table, "id");
  if (new_id < std::max<std::int32_t>(id_field.min, rules.first_id) ||
      new_id > std::min<std::int32_t>(id_field.max, rules.last_id)) {
    return unexpected(fmt::format("ID {} cannot be given: table {} takes IDs {}-{}", new_id, table.name,
                                  std::max<std::int32_t>(id_field.min, rules.first_id),
                                  std::min<std::int32_t>(id_field.max, rules.last_id)));
  }
  if (new_id == target.id) return unexpected(fmt::format("the servo already has ID {}", new_id));
  const bool broadcast = target.id == rules.broadcast_id;
  const std::uint32_t baud = link.settings().baud;

  if (!broadcast) {
    if (auto present = require_answer(link, target.id, " — is the baud right? `sms-gateway scan` finds servos");
        !present) {
      return unexpected(present.error());
    }
  }
  const LinkAnswer taken = ask_carefully(link, new_id);
  if (taken.status == LinkStatus::PortError) return unexpected(taken.detail);
  if (taken.ok() || taken.damaged) {  // a late answer of another ID is no sign
    return unexpected(fmt::format(
        "ID {} is already taken: a servo answers on it at {} bit/s. Two servos on one ID answer together and "
        "cannot be told apart; pick a free ID (`sms-gateway scan` lists the taken ones)",
        new_id, baud));
  }
  say(fmt::format("{} answers at {} bit/s; ID {} is free", who(target, rules), baud, new_id));

  auto lock = unlock(link, table, target.id, broadcast, say);
  if (!lock) return unexpected(lock.error());
  say(fmt::format("writing {} = {} (address {})", id_field.name, new_id, id_field.addr));
  if (auto written = write_field(link, table, target.id, id_field, new_id, true); !written) {
    (void)relock(link, table, target.id, *lock, say);
    return unexpected(written.error());
  }
  if (auto present = require_answer(link, new_id,
                                    " after the ID write: the write did not land; the servo "
                                    "should still answer on its old ID");
      !present) {
    return unexpected(present.error());
  }
  if (auto locked = relock(link, table, new_id, *lock, say); !locked) return unexpected(locked.error());
  auto stored = read_field(link, table, new_id, id_field);
  if (!stored) return unexpected(stored.error());
  if (*stored != new_id) {
    return unexpected(
        fmt::format("servo on ID {} reports {} = {}: the change did not hold", new_id, id_field.name, *stored));
  }
  if (!broadcast && ask_carefully(link, target.id).ok()) {
    return unexpected(fmt::format("ID {} answers as well as ID {}: two servos were on ID {}; one of them moved",
                                  target.id, new_id, target.id));
  }
  // Without a lock (d55d) EEPROM writes always persist; with one, it was open for the write.
  return fmt::format("{} now answers on ID {} at {} bit/s{}", who(target, rules), new_id, baud,
                     " (written with the EEPROM unlocked: kept over power-off)");
}

Expected<std::string> set_servo_baud(ServoLink& link, const ToolTarget& target, std::uint32_t new_baud,
                                     const Say& say) {
  if (auto checked = check_target(link, target, "set-baud"); !checked) return unexpected(checked.error());
  const TableSpec& table = modbus_map::table(target.table);
  const ToolProtocol& rules = tool_protocol(link.settings().protocol);
  const auto code = modbus_map::baud_code(rules.protocol, new_baud);
  if (!code) return unexpected(code.error());
  const FieldSpec& baud_field = require_field(table, "baud_rate");
  if (*code < baud_field.min || *code > baud_field.max) {
    return unexpected(
        fmt::format("{} bit/s is code {} of the {} baud table, but table {} takes codes {}-{} only "
                    "(docs/PROTOCOL.md §3: codes 8-11 need sts firmware 2.45 or later)",
                    new_baud, *code, protocol::to_string(rules.protocol), table.name, baud_field.min, baud_field.max));
  }
  const std::uint32_t old_baud = link.settings().baud;
  if (new_baud == old_baud) return unexpected(fmt::format("the line already runs at {} bit/s", new_baud));
  const bool broadcast = target.id == rules.broadcast_id;

  if (!broadcast) {
    if (auto present = require_answer(link, target.id, " — is the baud right? `sms-gateway scan` finds servos");
        !present) {
      return unexpected(present.error());
    }
    // At the new rate the ID must be free, or two servos would share it there.
    if (auto switched = link.set_baud(new_baud); !switched) return unexpected(switched.error());
    const LinkAnswer taken = ask_carefully(link, target.id);
    if (auto back = link.set_baud(old_baud); !back) return unexpected(back.error());
    if (taken.status == LinkStatus::PortError) return unexpected(taken.detail);
    if (taken.ok() || taken.damaged) {  // a late answer of another ID is no sign
      return unexpected(
          fmt::format("ID {} is already taken at {} bit/s: another servo answers there. Give one of "
                      "them another ID first (set-id)",
                      target.id, new_baud));
    }
    say(fmt::format("{} answers at {} bit/s; ID {} is free at {} bit/s", who(target, rules), old_baud, target.id,
                    new_baud));
  }

  auto lock = unlock(link, table, target.id, broadcast, say);
  if (!lock) return unexpected(lock.error());
  say(fmt::format("writing {} = {} ({} bit/s, address {})", baud_field.name, *code, new_baud, baud_field.addr));
  if (auto written = write_field(link, table, target.id, baud_field, *code, true); !written) {
    (void)relock(link, table, target.id, *lock, say);
    return unexpected(written.error());
  }
  if (auto switched = link.set_baud(new_baud); !switched) return unexpected(switched.error());
  if (broadcast) {
    if (auto locked = relock(link, table, target.id, *lock, say); !locked) return unexpected(locked.error());
    return fmt::format("sent to every servo: baud code {} ({} bit/s); check with `sms-gateway scan --baud {}`", *code,
                       new_baud, new_baud);
  }
  if (auto present = require_answer(
          link, target.id,
          " after the baud write: the servo may still run at " + std::to_string(old_baud) + " bit/s (try scan)");
      !present) {
    return unexpected(present.error());
  }
  if (auto locked = relock(link, table, target.id, *lock, say); !locked) return unexpected(locked.error());
  auto stored = read_field(link, table, target.id, baud_field);
  if (!stored) return unexpected(stored.error());
  if (*stored != *code) {
    return unexpected(fmt::format("servo {} answers at {} bit/s but reports {} = {}, not {}", target.id, new_baud,
                                  baud_field.name, *stored, *code));
  }
  return fmt::format(
      "servo {} now answers at {} bit/s (code {}), kept over power-off; set `baud: {}` on its bus in the gateway "
      "configuration",
      target.id, new_baud, *code, new_baud);
}

Expected<std::string> calibrate_middle(ServoLink& link, const ToolTarget& target, const Say& say) {
  if (auto checked = check_target(link, target, "calibrate-middle"); !checked) return unexpected(checked.error());
  const TableSpec& table = modbus_map::table(target.table);
  const auto calibration = std::find_if(kCalibrations.begin(), kCalibrations.end(),
                                        [&](const MidpointCalibration& entry) { return entry.table == table.id; });
  if (calibration == kCalibrations.end()) {
    return unexpected(
        fmt::format("table {} has no documented mid-point calibration (sts: 128 to torque_enable; "
                    "smsmb: fault_reset bit 2)",
                    table.name));
  }
  const ToolProtocol& rules = tool_protocol(link.settings().protocol);
  const bool broadcast = target.id == rules.broadcast_id;
  if (!broadcast) {
    if (auto present = require_answer(link, target.id, ""); !present) return unexpected(present.error());
  }
  const FieldSpec& field = require_field(table, calibration->field);
  say(fmt::format("writing {}", calibration->what));
  if (auto written = write_field(link, table, target.id, field, static_cast<std::uint32_t>(calibration->value));
      !written) {
    return unexpected(written.error());
  }
  if (broadcast) return std::string("sent to every servo: each one's present position is now its centre");
  auto position = read_field(link, table, target.id, require_field(table, "present_position"));
  if (!position) return unexpected(position.error());
  return fmt::format("servo {} calibrated: present position now {}", target.id, *position);
}

Expected<std::string> factory_reset(ServoLink& link, const ToolTarget& target, const Say& say) {
  if (auto checked = check_target(link, target, "factory-reset"); !checked) return unexpected(checked.error());
  const TableSpec& table = modbus_map::table(target.table);
  const ToolProtocol& rules = tool_protocol(link.settings().protocol);
  if (!rules.factory_reset) {
    return unexpected(fmt::format(
        "{} servos have no factory-reset instruction (feetech's RECOVERY restores the servo's own backup, "
        "not factory values): write the fields you need on the servo page, or with `sms-gateway set-id` / `set-baud`",
        protocol::to_string(rules.protocol)));
  }
  if (target.id == rules.broadcast_id) {
    return unexpected(std::string("a factory reset goes to one servo: every servo would come back on the same ID"));
  }
  // Where the servo will answer afterwards: the table's factory ID, at the rate its factory baud
  // code means (d55d code 0: 115200 on base motors, 9600 on the others).
  const FieldSpec& id_field = require_field(table, "id");
  const FieldSpec& baud_field = require_field(table, "baud_rate");
  const auto factory_id = static_cast<std::uint8_t>(id_field.default_value.value_or(1));
  const auto code = static_cast<std::uint8_t>(baud_field.default_value.value_or(0));
  std::vector<std::uint32_t> factory_bauds;
  for (const bool base_motor : {false, true}) {
    const auto bps = modbus_map::baud_from_code(rules.protocol, code, base_motor);
    if (bps && std::find(factory_bauds.begin(), factory_bauds.end(), *bps) == factory_bauds.end()) {
      factory_bauds.push_back(*bps);
    }
  }
  const std::uint32_t baud = link.settings().baud;
  if (auto present = require_answer(link, target.id, " — is the baud right? `sms-gateway scan` finds servos");
      !present) {
    return unexpected(present.error());
  }
  if (target.id != factory_id) {
    const LinkAnswer taken = ask_carefully(link, factory_id);
    if (taken.status == LinkStatus::PortError) return unexpected(taken.detail);
    if (taken.ok() || taken.damaged) {
      return unexpected(fmt::format(
          "ID {} (the factory ID) is already taken at {} bit/s: after the reset two servos would answer on it. "
          "Give that servo another ID first, or reset this one alone on the line",
          factory_id, baud));
    }
  }
  say(fmt::format("sending RESET to servo {}: every field back to its factory value, the ID to {}", target.id,
                  factory_id));
  const LinkAnswer reset = link.instruction(target.id, *rules.factory_reset);
  if (reset.status == LinkStatus::Refused || reset.status == LinkStatus::PortError) {
    return unexpected(fmt::format("servo {} did not take RESET: {}", target.id, reset.detail));
  }
  // It restarts with the factory values: look for it there.
  for (const std::uint32_t bps : factory_bauds) {
    if (bps != link.settings().baud) {
      if (auto switched = link.set_baud(bps); !switched) return unexpected(switched.error());
    }
    for (int attempt = 0; attempt < 3; ++attempt) {
      if (link.ping(factory_id).ok()) {
        return fmt::format("servo {} reset to factory values: it now answers as ID {} at {} bit/s", target.id,
                           factory_id, bps);
      }
    }
  }
  return unexpected(fmt::format(
      "RESET was sent to servo {}, but nothing answers on ID {} at {} bit/s: power-cycle the servo, then scan the line",
      target.id, factory_id, fmt::join(factory_bauds, " or ")));
}

Expected<std::vector<DumpRow>> dump_servo(ServoLink& link, const ToolTarget& target) {
  if (auto checked = check_target(link, target, "dump"); !checked) return unexpected(checked.error());
  const ToolProtocol& rules = tool_protocol(link.settings().protocol);
  if (target.id == rules.broadcast_id) return unexpected(std::string("nobody answers a READ to the broadcast ID"));
  const TableSpec& table = modbus_map::table(target.table);

  // Runs of addresses, each one READ: packet tables in chunks (gaps read along); SMSMB per run
  // of adjacent registers (a gap answers 0x02).
  struct Run {
    std::uint16_t address;
    std::uint16_t count;
  };
  std::vector<Run> runs;
  for (const FieldSpec& field : table.fields) {
    const std::uint16_t span = span_of(table, field);
    const std::uint16_t limit = table.addressing == Addressing::Register ? kMaxReadRegisters : kDumpChunkBytes;
    const bool adjacent = !runs.empty() && (table.addressing == Addressing::Byte ||
                                            runs.back().address + runs.back().count == field.addr);
    if (adjacent && field.addr + span - runs.back().address <= limit) {
      runs.back().count = static_cast<std::uint16_t>(field.addr + span - runs.back().address);
    } else {
      runs.push_back({field.addr, span});
    }
  }
  const std::uint8_t bytes_per_address = modbus_map::bytes_per_address(table.addressing);
  std::vector<DumpRow> rows;
  for (const Run& run : runs) {
    const LinkAnswer answer = link.read(target.id, run.address, run.count);
    if (!answer.ok()) {
      return unexpected(fmt::format("reading addresses {}-{} of servo {} failed: {}", run.address,
                                    run.address + run.count - 1, target.id, answer.detail));
    }
    for (const FieldSpec& field : table.fields) {
      if (field.addr < run.address || field.addr + span_of(table, field) > run.address + run.count) continue;
      const std::size_t offset = std::size_t{static_cast<std::uint16_t>(field.addr - run.address)} * bytes_per_address;
      const std::uint32_t raw =
          modbus_map::load_raw(std::span(answer.data).subspan(offset, field.size), field.size, order_of(table));
      rows.push_back({&field, raw, modbus_map::decode_value(field, raw)});
    }
  }
  return rows;
}

std::string format_dump(const TableSpec& table, const std::vector<DumpRow>& rows) {
  const bool registers = table.addressing == Addressing::Register;
  std::string text = fmt::format("{:>5}  {:<6}  {:<30}  {:>7}  {:<12}  {:<3}  {}\n", registers ? "reg" : "addr", "hex",
                                 "name", "value", "unit", "acc", "area");
  for (const DumpRow& row : rows) {
    const FieldSpec& field = *row.field;
    const std::string_view access = field.access == Access::ReadOnly    ? "R"
                                    : field.access == Access::WriteOnly ? "W"
                                                                        : "RW";
    text += fmt::format("{:>5}  0x{:<4X}  {:<30}  {:>7}  {:<12}  {:<3}  {}\n", field.addr, field.addr, field.name,
                        row.value, field.unit, access, field.area == modbus_map::Area::Eeprom ? "EEPROM" : "RAM");
  }
  return text;
}

}  // namespace sms::gateway
