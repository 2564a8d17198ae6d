#include "modbus_map/register_map_doc.h"

#include <bit>
#include <string_view>

#include "modbus_map/baud_tables.h"
#include "modbus_map/motion.h"
#include "modbus_map/register_map.h"
#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

std::string_view access_text(Access access) {
  switch (access) {
    case Access::ReadOnly: return "R";
    case Access::WriteOnly: return "W";
    case Access::ReadWrite: return "RW";
  }
  return "";
}

std::string encoding_text(const Encoding& encoding) {
  switch (encoding.kind) {
    case EncodingKind::Unsigned: return "unsigned";
    case EncodingKind::SignMagnitude: return "sign-magnitude, bit " + std::to_string(encoding.sign_bit);
    case EncodingKind::TwosComplement: return "two's complement";
  }
  return "";
}

std::string field_range_text(const FieldSpec& field) {
  if (field.allowed_values.empty()) return range_text(field.min, field.max);
  std::string text;
  for (const std::int32_t value : field.allowed_values) text += (text.empty() ? "" : ", ") + std::to_string(value);
  return text;
}

std::string_view bit_space_text(BitSpace space) {
  switch (space) {
    case BitSpace::None: return "";
    case BitSpace::Coil: return "coil";
    case BitSpace::DiscreteInput: return "discrete input";
  }
  return "";
}

std::string protocol_text(const TableSpec& table) { return std::string(protocol::to_string(table.protocol)); }

// `name` in backticks, built by appending (GCC 12 -O3 misreads "`" + std::string(...) as an
// overlapping memcpy: -Wrestrict, GCC bug 105651).
std::string code(std::string_view name) {
  std::string text(1, '`');
  text.append(name);
  text.push_back('`');
  return text;
}

}  // namespace

std::string enabling_writes_text(TableId id) {
  const MotionSpec& motion = motion_spec(id);
  std::string text;
  for (const EnableField& enable : motion.enables) {
    text += (text.empty() ? "" : ", ") + code(enable.field) + " := " + std::to_string(enable.on) + " (" +
            std::string(enable.what) + ")";
  }
  const auto drive = drive_fields(motion);
  text += (text.empty() ? "a write of " : "; a write of ");
  for (std::size_t i = 0; i < drive.size(); ++i) text += (i == 0 ? "" : " or ") + code(drive[i]);
  text += " that changes the drive";
  return text;
}

namespace {

// docs/PLC_GUIDE.md "Safety": what the watchdog and the e-stop treat as motion, and how they stop a servo.
void safety_text(std::string& out, const TableSpec& spec) {
  const MotionSpec& motion = motion_spec(spec.id);
  const auto names = [](auto&& items, auto&& text_of) {
    std::string text;
    for (const auto& item : items) {
      if (!text.empty()) text += ", ";
      text += text_of(item);
    }
    return text;
  };
  out += "Safety: motion writes (refused with 0x04 while the e-stop is latched or the bus's watchdog is tripped): ";
  out += names(motion.motion_fields, [](std::string_view name) { return code(name); });
  out += "; writes that only stop (allowed then): ";
  out += names(motion.stopping_writes,
               [](const StoppingWrite& w) { return code(w.field) + " = " + std::to_string(w.value); });
  out += ". Safe stop default " + code(to_string(motion.default_stop)) + ": ";
  const BusRange block = goal_block(motion);
  std::string ramp;  // "`acceleration` := 0"
  for (const RampField& field : motion.stop_ramp) {
    ramp += (ramp.empty() ? "" : ", ") + code(field.field) + " := " + std::to_string(field.fastest);
  }
  out += "`hold` rewrites " + address_text(spec, block.address) + ".." + address_text(spec, block.end() - 1) + " (" +
         (ramp.empty() ? std::string("no stop ramp: the servo changes speed at once")
                       : "the stop ramp " + ramp + " or `stop_deceleration`, in the same frame") +
         "; position mode: `" + std::string(motion.goal_position) + "` := `" + std::string(motion.present_position) +
         "`" + (ramp.empty() ? std::string() : " + the run-on at that ramp") + "; speed mode: `" +
         std::string(motion.goal_speed) + "` := 0" +
         (motion.goal_time.empty() ? std::string() : "; PWM mode: `" + std::string(motion.goal_time) + "` := 0") +
         (motion.mode.empty() ? "; speed mode = both angle limits 0" : "; step mode: torque off") +
         "), `torque_off` writes `" + std::string(motion.torque_off.field) +
         "` = " + std::to_string(motion.torque_off.value) +
         ". No jump on enable (docs/SAFETY.md): the hold goes first when a write enables a disabled motor "
         "or changes the drive of an enabled one: " +
         enabling_writes_text(spec.id) + ".\n\n";
}

// The status byte's bits by name, as the console, the bus monitor and refusal reasons show them.
void status_bits_text(std::string& out, const TableSpec& spec) {
  out += "Status bits (";
  if (spec.addressing == Addressing::Byte) out += "the ERROR byte of every answer";
  if (const FieldSpec* field = field_by_name(spec, spec.status_field)) {
    out += std::string(spec.addressing == Addressing::Byte ? ", and " : "the low byte of ") + "`" +
           std::string(field->name) + "` (" + address_text(spec, field->addr) + ")";
  }
  out += "): ";
  bool first = true;
  for (const StatusBit& bit : spec.status_bits) {
    out += (first ? "" : ", ") + std::string("bit ") + std::to_string(std::countr_zero(bit.mask)) + " `" +
           std::string(bit.name) + "`" + (bit.fault ? "" : " (a state, no fault)");
    first = false;
  }
  out += ".\n\n";
}

void native_table(std::string& out, const TableSpec& spec) {
  const BusRange poll = default_poll_block(spec.id);
  out += "### Table `" + std::string(spec.name) + "`: " + std::string(spec.title) + "\n\n";
  out += "Bus protocol `" + protocol_text(spec) + "`; ";
  if (spec.addressing == Addressing::Byte) {
    out += std::string("byte addresses, two-byte fields ") +
           (spec.default_byte_order == ByteOrder::LowFirst ? "low byte first" : "high byte first") +
           " (overridable per servo); one register per field at its first address.";
  } else {
    out += "one 16-bit register per field, high byte first (Modbus order).";
  }
  out += " SYNC READ: " + std::string(spec.has_sync_read ? "yes" : "no") +
         ". Default poll block (input registers): " + address_text(spec, poll.address) + ".." +
         address_text(spec, poll.end() - 1) + ".\n\n";
  safety_text(out, spec);
  out += "| addr | name | access | size | area | unit | encoding | range | default | bit | notes |\n";
  out += "|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const FieldSpec& field : spec.fields) {
    out += "| " + address_text(spec, field.addr) + " | `" + std::string(field.name) + "` | " +
           std::string(access_text(field.access)) + " | " + std::to_string(field.size) + " | " +
           (field.area == Area::Eeprom ? "EEPROM" : "RAM") + " | " + std::string(field.unit) + " | " +
           encoding_text(field.encoding) + " | " + field_range_text(field) + " | " +
           (field.default_value ? std::to_string(*field.default_value) : std::string()) + " | " +
           std::string(bit_space_text(field.bit_space)) + " | " + std::string(field.notes) + " |\n";
  }
  out += "\n";
  status_bits_text(out, spec);
}

std::string entry_access_text(const RegisterEntry& entry) {
  if (entry.readable && entry.writable) return "RW";
  if (entry.readable) return "R";
  if (entry.writable) return "W";
  return "-";
}

std::string counterpart_text(const TableSpec& servo, const RegisterEntry& entry) {
  if (entry.counterpart == nullptr) return "none: 0x02";
  std::string text = address_text(servo, entry.counterpart->addr) + " `" + std::string(entry.counterpart->name) + "`";
  if (entry.link->conversion == Conversion::BytePair) {
    const FieldSpec* low = field_at(servo, entry.link->low_field_addr);
    text += ", " + address_text(servo, low->addr) + " `" + std::string(low->name) + "`";
  }
  return text;
}

std::string conversion_text(const RegisterEntry& entry) {
  if (entry.link == nullptr) return "";
  const CounterpartLink& link = *entry.link;
  switch (link.conversion) {
    case Conversion::Same:
      if (entry.counterpart->encoding.kind == EncodingKind::SignMagnitude) {
        return "as is (two's complement here, sign-magnitude bit " +
               std::to_string(entry.counterpart->encoding.sign_bit) + " on the bus)";
      }
      return "as is";
    case Conversion::Scale:
      if (link.scale_den == 1) return "register = field × " + std::to_string(link.scale_num);
      return "register = field ÷ " + std::to_string(link.scale_den) + " (rounded)";
    case Conversion::ValueMap: {
      std::string text;
      for (const ValueMapping& mapping : link.values) {
        text += text.empty() ? "" : ", ";
        const std::string r = std::to_string(mapping.register_value);
        const std::string f = std::to_string(mapping.field_value);
        switch (mapping.direction) {
          case MapDirection::Both: text += r + " ↔ " + f; break;
          case MapDirection::ReadOnly: text += r + " ← " + f + " (read only)"; break;
          case MapDirection::WriteOnly: text += r + " → " + f + " (write only)"; break;
        }
      }
      return text + "; other values: 0x03";
    }
    case Conversion::BaudRate:
      return "Modbus code ↔ bit rate ↔ feetech code; 0x03 for a rate the servo cannot run; reads " +
             std::to_string(kNoModbusBaudCode) + " when its rate has no Modbus code";
    case Conversion::StatusBits: {
      static constexpr char kDigits[] = "0123456789ABCDEF";
      const std::string mask{'0', 'x', kDigits[(link.status_mask >> 4) & 0xF], kDigits[link.status_mask & 0xF]};
      return "bits of the field under mask " + mask;
    }
    case Conversion::BytePair: return "first field high byte, second low byte";
    case Conversion::FaultReset:
      return "bit 2 → writes " + std::to_string(kCalibrateTorqueValue) + " to `" +
             std::string(entry.counterpart->name) + "`; bits 0, 1, 5, 6, 7 accepted without a bus write; others 0x03";
  }
  return "";
}

void smsmb_profile(std::string& out, const RegisterMap& map) {
  const TableSpec& servo = map.servo_table();
  const TableSpec& shown = map.shown_table();
  out += "### Profile `smsmb` over table `" + std::string(servo.name) + "`\n\n";
  out += "| reg | name | access | counterpart | conversion | range | unit | bit | notes |\n";
  out += "|---|---|---|---|---|---|---|---|---|\n";
  for (const RegisterEntry& entry : map.entries()) {
    const std::string range = entry.writable ? range_text(entry.min, entry.max) : std::string();
    std::string notes(entry.link != nullptr ? entry.link->notes : std::string_view());
    out += "| " + address_text(shown, entry.address) + " | `" + std::string(entry.shown->name) + "` | " +
           entry_access_text(entry) + " | " + counterpart_text(servo, entry) + " | " + conversion_text(entry) + " | " +
           range + " | " + std::string(entry.shown->unit) + " | " +
           std::string(entry.counterpart != nullptr ? bit_space_text(entry.shown->bit_space) : "") + " | " + notes +
           " |\n";
  }
  out += "\n";
}

void baud_table_text(std::string& out, protocol::BusProtocol protocol) {
  out += "| code | `" + std::string(protocol::to_string(protocol)) + "` bit/s |\n|---|---|\n";
  if (protocol == protocol::BusProtocol::D55d) {
    out += "| 0 | " + std::to_string(*baud_from_code(protocol, 0, true)) + " on base motors, " +
           std::to_string(*baud_from_code(protocol, 0, false)) + " on others |\n";
  }
  for (const BaudEntry& entry : baud_table(protocol)) {
    out += "| " + std::to_string(entry.code) + " | " + std::to_string(entry.bps) + " |\n";
  }
  out += "\n";
}

}  // namespace

std::string register_map_markdown() {
  std::string out;
  out += "# Register map\n\n";
  out +=
      "<!-- Generated by gen-register-map from modbus_map/ (tables, smsmb links, baud tables). Do not edit:\n"
      "     run build/bin/gen-register-map docs/REGISTER_MAP.md -->\n\n";
  out +=
      "What a Modbus TCP client sees of each servo unit. The rules are in `docs/PLC_GUIDE.md` (the contract);\n"
      "this page lists every address. Addresses are the zero-based protocol addresses on the wire.\n\n"
      "- Holding registers (FC03 read live, FC06/FC16 write) and input registers (FC04, from the poll cache)\n"
      "  share the addresses below. A two-byte field is one register at its first address; its second\n"
      "  address and addresses that are no field read as 0.\n"
      "- Signed values (sign-magnitude or two's complement on the bus) are two's-complement int16 on Modbus.\n"
      "- Packet buses (feetech, d55d): holding register 512 + a is the staged write (REG WRITE) of field a;\n"
      "  gateway coil 0 runs every staged write (ACTION). A staged write of a motion field is a motion write.\n"
      "- Safety (README \"Safety\"): gateway coil 1 is the e-stop latch (1 stops every bus and refuses motion\n"
      "  writes with 0x04, 0 resets), coil 2 re-arms tripped watchdogs (write 0); holding register 1000 + n is\n"
      "  bus n's watchdog heartbeat. Each table below names its motion writes and its safe stop.\n"
      "- Input registers serve the bus's poll block only (the default block is given per table); FC02\n"
      "  discrete inputs come from the poll cache when it holds them, else from the servo.\n"
      "- Exceptions: 0x02 for an address beyond the table, a read-only field, a write touching only gaps or\n"
      "  second bytes, a register without counterpart, a quantity over the Modbus limits (125 / 123 registers,\n"
      "  2000 / 1968 coils); 0x03 for a value outside the range column.\n\n";

  out += "## Profile `native`\n\n";
  for (const TableSpec* spec : all_tables()) native_table(out, *spec);

  out += "## Profile `smsmb`\n\n";
  out +=
      "Feetech's SMSMB register map (table `smsmb` above) shown for servos of tables `sts` and `sms1` on\n"
      "feetech buses. Each register is linked to its counterpart field; the range column is what a write\n"
      "accepts (the SMSMB range cut to what the counterpart holds). Registers without a counterpart read as 0\n"
      "inside a longer read and answer 0x02 alone or in any write. Input registers 0x100-0x107 come from the\n"
      "poll cache (the servo's block 56-70).\n\n";
  for (const TableSpec* spec : all_tables()) {
    if (smsmb_links(spec->id).empty()) continue;
    const auto map = RegisterMap::create(spec->id, Profile::Smsmb);
    if (map) smsmb_profile(out, *map);
  }

  out += "## Baud tables\n\n";
  out +=
      "Codes per bus protocol (docs/PROTOCOL.md §3). In the smsmb profile, register 0x0B speaks the `modbus-rtu` "
      "column\n"
      "and is translated through the bit rate to the servo's `feetech` code.\n\n";
  for (const auto protocol :
       {protocol::BusProtocol::Feetech, protocol::BusProtocol::ModbusRtu, protocol::BusProtocol::D55d}) {
    baud_table_text(out, protocol);
  }
  return out;
}

}  // namespace sms::modbus_map
