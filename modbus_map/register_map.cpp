#include "modbus_map/register_map.h"

#include <algorithm>
#include <array>
#include <utility>

#include "modbus_map/baud_tables.h"
#include "modbus_map/tables.h"
#include "modbus_map/tables/smsmb_links.h"
#include "protocol/hex_text.h"
#include "protocol/modbus_pdu.h"

namespace sms::modbus_map {
namespace {

using protocol::BusProtocol;
using protocol::Bytes;

struct ProfileName {
  Profile profile;
  std::string_view name;
};
constexpr std::array kProfileNames{
    ProfileName{Profile::Native, "native"},
    ProfileName{Profile::Smsmb, "smsmb"},
};

// The feedback block of each table (docs/PROTOCOL.md §5 example: sts 56-70 is one SYNC READ of 15 bytes).
struct PollBlockDefault {
  TableId table;
  BusRange block;
};
constexpr std::array kDefaultPollBlocks{
    PollBlockDefault{TableId::Sts, {56, 15}},  PollBlockDefault{TableId::Sms1, {56, 15}},
    PollBlockDefault{TableId::D55d, {36, 14}}, PollBlockDefault{TableId::Smsmb, kSmsmbFeedbackRegisters},
    PollBlockDefault{TableId::Scs, {56, 15}},
};

Unexpected<MapError> fail(ModbusException code, std::string message) {
  return unexpected(MapError{code, std::move(message)});
}
Unexpected<MapError> bad_address(std::string message) {
  return fail(ModbusException::IllegalDataAddress, std::move(message));
}
Unexpected<MapError> bad_value(std::string message) {
  return fail(ModbusException::IllegalDataValue, std::move(message));
}

// value × num / den, rounded half away from zero.
std::int32_t scale_round(std::int64_t value, std::int64_t num, std::int64_t den) {
  const std::int64_t product = value * num;
  const std::int64_t magnitude = ((product < 0 ? -product : product) + den / 2) / den;
  return static_cast<std::int32_t>(product < 0 ? -magnitude : magnitude);
}

std::string_view space_name(RequestSpace space) {
  switch (space) {
    case RequestSpace::HoldingRegisters: return "holding registers";
    case RequestSpace::InputRegisters: return "input registers";
    case RequestSpace::Coils: return "coils";
    case RequestSpace::DiscreteInputs: return "discrete inputs";
  }
  return "registers";
}

bool is_bit_space(RequestSpace space) { return space == RequestSpace::Coils || space == RequestSpace::DiscreteInputs; }

// The bytes of the bus ranges a plan read, looked up by bus address.
class BusImage {
 public:
  BusImage(std::span<const BusRange> ranges, std::span<const Bytes> replies, std::uint8_t bytes_per_address)
      : ranges_(ranges), replies_(replies), bytes_per_address_(bytes_per_address) {}

  std::optional<std::span<const std::uint8_t>> bytes(std::uint16_t address, std::uint16_t addresses) const {
    const BusRange wanted{address, addresses};
    for (std::size_t i = 0; i < ranges_.size(); ++i) {
      if (!ranges_[i].contains(wanted)) continue;
      const std::size_t offset = static_cast<std::size_t>(address - ranges_[i].address) * bytes_per_address_;
      return std::span<const std::uint8_t>(replies_[i]).subspan(offset, std::size_t{addresses} * bytes_per_address_);
    }
    return std::nullopt;
  }

 private:
  std::span<const BusRange> ranges_;
  std::span<const Bytes> replies_;
  std::uint8_t bytes_per_address_;
};

}  // namespace

std::string_view to_string(ModbusException code) {
  return protocol::modbus_exception_name(static_cast<std::uint8_t>(code));
}

std::string to_string(const MapError& error) {
  const auto code = static_cast<std::uint8_t>(error.code);
  return "exception " + protocol::hex_number(code) + " (" + std::string(protocol::modbus_exception_name(code)) +
         "): " + error.message;
}

std::string_view to_string(Profile profile) {
  for (const auto& entry : kProfileNames) {
    if (entry.profile == profile) return entry.name;
  }
  return "unknown";
}

std::optional<Profile> profile_from_name(std::string_view name) {
  for (const auto& entry : kProfileNames) {
    if (entry.name == name) return entry.profile;
  }
  return std::nullopt;
}

BusRange default_poll_block(TableId table_id) {
  for (const auto& entry : kDefaultPollBlocks) {
    if (entry.table == table_id) return entry.block;
  }
  return {};
}

Expected<BusRange> poll_block_for_fields(TableId table_id, std::span<const std::string> field_names) {
  const TableSpec& spec = table(table_id);
  if (field_names.empty()) return unexpected(std::string("no poll fields given for table ") + std::string(spec.name));
  std::uint32_t low = UINT32_MAX;
  std::uint32_t high = 0;
  for (const std::string& name : field_names) {
    const FieldSpec* field = field_by_name(spec, name);
    if (field == nullptr) {
      std::string known;
      for (const FieldSpec& candidate : spec.fields) {
        if (candidate.access == Access::WriteOnly) continue;
        known += (known.empty() ? "" : ", ") + std::string(candidate.name);
      }
      return unexpected("table " + std::string(spec.name) + " has no field '" + name +
                        "' to poll; its readable fields: " + known);
    }
    if (field->access == Access::WriteOnly) {
      return unexpected("field '" + name + "' of table " + std::string(spec.name) +
                        " is write-only and cannot be polled");
    }
    low = std::min<std::uint32_t>(low, field->addr);
    high = std::max<std::uint32_t>(high, field->addr + address_span(spec.addressing, *field));
  }
  return BusRange{static_cast<std::uint16_t>(low), static_cast<std::uint16_t>(high - low)};
}

std::span<const CounterpartLink> smsmb_links(TableId servo_table) {
  switch (servo_table) {
    case TableId::Sts: return tables::kStsSmsmbLinks;
    case TableId::Sms1: return tables::kSms1SmsmbLinks;
    // scs: 10-bit positions and its own speed unit; an SMSMB program would drive it wrong.
    case TableId::Scs:
    case TableId::D55d:
    case TableId::Smsmb: break;
  }
  return {};
}

// --- construction ----------------------------------------------------------------------------------

Expected<RegisterMap> RegisterMap::create(TableId table_id, Profile profile, std::optional<ByteOrder> byte_order) {
  const TableSpec& servo = table(table_id);
  if (byte_order && servo.addressing == Addressing::Register && *byte_order != ByteOrder::HighFirst) {
    return unexpected("table " + std::string(servo.name) +
                      ": Modbus registers are high byte first; a byte-order override applies to packet tables only");
  }
  RegisterMap map;
  map.servo_table_ = &servo;
  map.profile_ = profile;
  map.byte_order_ = byte_order.value_or(servo.default_byte_order);

  if (profile == Profile::Native) {
    map.shown_table_ = &servo;
    map.description_ = "table " + std::string(servo.name);
    for (const FieldSpec& field : servo.fields) {
      map.entries_.push_back(RegisterEntry{.address = field.addr,
                                           .shown = &field,
                                           .counterpart = &field,
                                           .link = nullptr,
                                           .readable = field.access != Access::WriteOnly,
                                           .writable = field.access != Access::ReadOnly,
                                           .min = field.min,
                                           .max = field.max});
    }
    return map;
  }

  const std::span<const CounterpartLink> links = smsmb_links(table_id);
  if (links.empty()) {
    return unexpected("the smsmb profile shows servos of tables sts and sms1 (feetech buses) as SMSMB servos; table " +
                      std::string(servo.name) + " has the native profile only" +
                      (table_id == TableId::Smsmb ? " (its native map already is the SMSMB map)" : ""));
  }
  map.shown_table_ = &table(TableId::Smsmb);
  map.description_ = "smsmb profile of table " + std::string(servo.name);
  for (const FieldSpec& shown : map.shown_table_->fields) {
    RegisterEntry entry{.address = shown.addr, .shown = &shown, .min = shown.min, .max = shown.max};
    const auto link = std::find_if(links.begin(), links.end(),
                                   [&](const CounterpartLink& candidate) { return candidate.reg == shown.addr; });
    if (link != links.end()) {
      const FieldSpec* counterpart = field_at(servo, link->field_addr);
      entry.counterpart = counterpart;
      entry.link = &*link;
      const bool derived = link->conversion == Conversion::StatusBits || link->conversion == Conversion::BytePair;
      entry.readable = shown.access != Access::WriteOnly && counterpart->access != Access::WriteOnly &&
                       link->conversion != Conversion::FaultReset;
      entry.writable = shown.access != Access::ReadOnly && counterpart->access != Access::ReadOnly && !derived;
      switch (link->conversion) {
        case Conversion::Same:
          entry.min = std::max(shown.min, counterpart->min);
          entry.max = std::min(shown.max, counterpart->max);
          break;
        case Conversion::Scale:
          // What the counterpart can hold, in register units (truncated toward zero: exact).
          entry.min = std::max(shown.min, counterpart->min * link->scale_num / link->scale_den);
          entry.max = std::min(shown.max, counterpart->max * link->scale_num / link->scale_den);
          break;
        case Conversion::ValueMap: {
          bool first = true;
          for (const ValueMapping& mapping : link->values) {
            if (mapping.direction == MapDirection::ReadOnly) continue;
            entry.min = first ? mapping.register_value : std::min(entry.min, mapping.register_value);
            entry.max = first ? mapping.register_value : std::max(entry.max, mapping.register_value);
            first = false;
          }
          break;
        }
        case Conversion::BaudRate:
        case Conversion::StatusBits:
        case Conversion::BytePair:
        case Conversion::FaultReset: break;  // the shown register's own range; the conversion checks the rest
      }
    }
    map.entries_.push_back(entry);
  }
  return map;
}

bool RegisterMap::supports_staged_writes() const { return servo_table_->protocol != BusProtocol::ModbusRtu; }

const RegisterEntry* RegisterMap::entry_covering(std::uint16_t address) const {
  const FieldSpec* field = field_covering(*shown_table_, address);
  if (field == nullptr) return nullptr;
  return &entries_[static_cast<std::size_t>(field - shown_table_->fields.data())];
}

const RegisterEntry* RegisterMap::entry_at(std::uint16_t address) const {
  const RegisterEntry* entry = entry_covering(address);
  return entry != nullptr && entry->address == address ? entry : nullptr;
}

bool RegisterMap::in_space(const RegisterEntry& entry, RequestSpace space) const {
  switch (space) {
    case RequestSpace::HoldingRegisters:
    case RequestSpace::InputRegisters: return true;
    case RequestSpace::Coils: return entry.shown->bit_space == BitSpace::Coil;
    case RequestSpace::DiscreteInputs: return entry.shown->bit_space == BitSpace::DiscreteInput;
  }
  return false;
}

std::string RegisterMap::address_label(std::uint16_t address) const { return address_text(*shown_table_, address); }

std::string RegisterMap::field_label(const FieldSpec& field) const {
  return std::string(field.name) + " (" + address_label(field.addr) + ")";
}

// --- reads -------------------------------------------------------------------------------------------

MapResult<ReadPlan> RegisterMap::plan_holding_read(std::uint16_t start, std::uint16_t count) const {
  return plan_read(RequestSpace::HoldingRegisters, start, count, std::nullopt);
}

MapResult<ReadPlan> RegisterMap::plan_input_read(std::uint16_t start, std::uint16_t count, BusRange poll_block) const {
  return plan_read(RequestSpace::InputRegisters, start, count, poll_block);
}

MapResult<ReadPlan> RegisterMap::plan_coil_read(std::uint16_t start, std::uint16_t count) const {
  return plan_read(RequestSpace::Coils, start, count, std::nullopt);
}

MapResult<ReadPlan> RegisterMap::plan_discrete_read(std::uint16_t start, std::uint16_t count,
                                                    std::optional<BusRange> poll_block) const {
  return plan_read(RequestSpace::DiscreteInputs, start, count, poll_block);
}

MapResult<ReadPlan> RegisterMap::plan_read(RequestSpace space, std::uint16_t start, std::uint16_t count,
                                           std::optional<BusRange> poll_block) const {
  const std::uint16_t limit = is_bit_space(space) ? modbus_limits::kReadBits : modbus_limits::kReadRegisters;
  if (count == 0 || count > limit) {  // the quantity first, 0x03, as the Modbus application protocol
    return bad_value("read of " + std::to_string(count) + " " + std::string(space_name(space)) +
                     ": the quantity must be 1.." + std::to_string(limit));
  }
  const std::uint32_t end = std::uint32_t{start} + count;
  const std::uint16_t table_end = end_address(*shown_table_);
  if (end > table_end) {
    return bad_address(std::string(space_name(space)) + " " + address_label(start) + ".." + address_label(end - 1) +
                       " reach beyond " + description_ + " (last address " + address_label(table_end - 1) + ")");
  }
  if (space == RequestSpace::InputRegisters) {
    const BusRange window = profile_ == Profile::Native ? poll_block.value_or(BusRange{}) : kSmsmbFeedbackRegisters;
    if (!window.contains(BusRange{start, count})) {
      return bad_address("input registers " + address_label(start) + ".." + address_label(end - 1) + " of " +
                         description_ + ": input registers serve the polled block " + address_label(window.address) +
                         ".." + address_label(window.end() - 1) +
                         " only; read holding registers (FC03) for live values");
    }
  }

  std::vector<std::uint16_t> addresses;  // bus addresses the values need
  const RegisterEntry* first_unlinked = nullptr;
  const auto need = [&](const FieldSpec& field) -> MapResult<Ok> {
    const std::uint16_t span = address_span(servo_table_->addressing, field);
    if (space == RequestSpace::InputRegisters && !poll_block->contains(BusRange{field.addr, span})) {
      return bad_address("input register data of " + description_ + ": servo field " + std::string(field.name) + " (" +
                         address_text(*servo_table_, field.addr) + ") is outside the poll block " +
                         address_text(*servo_table_, poll_block->address) + ".." +
                         address_text(*servo_table_, poll_block->end() - 1) + "; add it to the bus's poll fields");
    }
    for (std::uint16_t i = 0; i < span; ++i) addresses.push_back(static_cast<std::uint16_t>(field.addr + i));
    return Ok{};
  };
  for (std::uint32_t address = start; address < end; ++address) {
    const RegisterEntry* entry = entry_at(static_cast<std::uint16_t>(address));
    if (entry == nullptr || !in_space(*entry, space)) continue;
    if (entry->counterpart == nullptr) {
      if (first_unlinked == nullptr) first_unlinked = entry;
      continue;
    }
    if (!entry->readable) continue;
    if (auto ok = need(*entry->counterpart); !ok) return unexpected(ok.error());
    if (entry->link != nullptr && entry->link->conversion == Conversion::BytePair) {
      if (auto ok = need(*field_at(*servo_table_, entry->link->low_field_addr)); !ok) return unexpected(ok.error());
    }
  }

  ReadPlan plan{.space = space, .start = start, .count = count, .source = ReadSource::Bus, .reads = {}};
  if (addresses.empty()) {
    if (is_bit_space(space)) {
      std::string listed;
      for (const RegisterEntry& entry : entries_) {
        if (in_space(entry, space) && entry.counterpart != nullptr) {
          listed += (listed.empty() ? "" : ", ") + address_label(entry.address) + " " + std::string(entry.shown->name);
        }
      }
      return bad_address(std::string(space_name(space)) + " " + address_label(start) + ".." + address_label(end - 1) +
                         " of " + description_ + " hold none; " + std::string(space_name(space)) + ": " +
                         (listed.empty() ? "none" : listed));
    }
    if (first_unlinked != nullptr) {
      return bad_address(field_label(*first_unlinked->shown) + " has no counterpart in table " +
                         std::string(servo_table_->name) + " (" + description_ + ")");
    }
    return plan;  // only gaps: zeros, no bus traffic
  }
  std::sort(addresses.begin(), addresses.end());
  addresses.erase(std::unique(addresses.begin(), addresses.end()), addresses.end());

  const bool from_cache =
      space == RequestSpace::InputRegisters ||
      (space == RequestSpace::DiscreteInputs && poll_block &&
       poll_block->contains(
           BusRange{addresses.front(), static_cast<std::uint16_t>(addresses.back() - addresses.front() + 1)}));
  plan.source = from_cache ? ReadSource::PollCache : ReadSource::Bus;
  if (!from_cache && servo_table_->addressing == Addressing::Register) {
    // A Modbus-RTU servo may refuse a read over registers it does not have: one FC03 per run.
    for (const std::uint16_t address : addresses) {
      if (!plan.reads.empty() && plan.reads.back().end() == address) {
        ++plan.reads.back().count;
      } else {
        plan.reads.push_back(BusRange{address, 1});
      }
    }
  } else {
    // Packet servos read any byte of their memory: one READ covers the range, gaps included.
    plan.reads.push_back(
        BusRange{addresses.front(), static_cast<std::uint16_t>(addresses.back() - addresses.front() + 1)});
  }
  return plan;
}

namespace {

// The register value of one readable entry from the bus image.
MapResult<std::uint16_t> read_register(const RegisterEntry& entry, const TableSpec& servo, ByteOrder order,
                                       const BusImage& image) {
  const auto raw_of = [&](const FieldSpec& field) -> MapResult<std::uint32_t> {
    const auto bytes = image.bytes(field.addr, address_span(servo.addressing, field));
    if (!bytes) {
      return fail(ModbusException::ServerDeviceFailure, "servo field " + std::string(field.name) + " (" +
                                                            address_text(servo, field.addr) +
                                                            ") is not in the data read for this request");
    }
    return load_raw(*bytes, field.size, order);
  };
  const FieldSpec& field = *entry.counterpart;
  const auto raw = raw_of(field);
  if (!raw) return unexpected(raw.error());
  const std::int32_t field_value = decode_value(field, *raw);
  std::int32_t value = field_value;
  const Conversion conversion = entry.link != nullptr ? entry.link->conversion : Conversion::Same;
  switch (conversion) {
    case Conversion::Same:
    case Conversion::FaultReset: break;
    case Conversion::Scale: value = scale_round(field_value, entry.link->scale_num, entry.link->scale_den); break;
    case Conversion::ValueMap:
      for (const ValueMapping& mapping : entry.link->values) {
        if (mapping.direction != MapDirection::WriteOnly && mapping.field_value == field_value) {
          value = mapping.register_value;
          break;
        }
      }
      break;
    case Conversion::BaudRate: {
      value = kNoModbusBaudCode;
      if (field_value >= 0 && field_value <= 0xFF) {
        if (const auto bps = baud_from_code(servo.protocol, static_cast<std::uint8_t>(field_value))) {
          if (const auto code = baud_code(BusProtocol::ModbusRtu, *bps)) value = *code;
        }
      }
      break;
    }
    case Conversion::StatusBits: value = field_value & entry.link->status_mask; break;
    case Conversion::BytePair: {
      const auto low = raw_of(*field_at(servo, entry.link->low_field_addr));
      if (!low) return unexpected(low.error());
      value = (field_value & 0xFF) << 8 | static_cast<std::int32_t>(*low & 0xFF);
      break;
    }
  }
  return static_cast<std::uint16_t>(static_cast<std::uint32_t>(value));
}

}  // namespace

MapResult<std::vector<std::uint16_t>> RegisterMap::registers_from(const ReadPlan& plan,
                                                                  std::span<const Bytes> replies) const {
  if (replies.size() != plan.reads.size()) {
    return fail(ModbusException::ServerDeviceFailure, std::to_string(replies.size()) + " replies for a plan of " +
                                                          std::to_string(plan.reads.size()) + " reads");
  }
  for (std::size_t i = 0; i < replies.size(); ++i) {
    const std::size_t expected = std::size_t{plan.reads[i].count} * bytes_per_bus_address();
    if (replies[i].size() != expected) {
      return fail(ModbusException::ServerDeviceFailure, "servo answered " + std::to_string(replies[i].size()) +
                                                            " bytes to a READ of " + std::to_string(expected) + " at " +
                                                            address_text(*servo_table_, plan.reads[i].address) + " (" +
                                                            description_ + ")");
    }
  }
  const BusImage image(plan.reads, replies, bytes_per_bus_address());
  std::vector<std::uint16_t> values(plan.count, 0);
  for (std::uint16_t i = 0; i < plan.count; ++i) {
    const RegisterEntry* entry = entry_at(static_cast<std::uint16_t>(plan.start + i));
    if (entry == nullptr || entry->counterpart == nullptr || !entry->readable || !in_space(*entry, plan.space)) {
      continue;  // gaps, second bytes, write-only and unlinked registers read as 0
    }
    const auto value = read_register(*entry, *servo_table_, byte_order_, image);
    if (!value) return unexpected(value.error());
    values[i] = *value;
  }
  return values;
}

MapResult<std::vector<bool>> RegisterMap::bits_from(const ReadPlan& plan, std::span<const Bytes> replies) const {
  const auto values = registers_from(plan, replies);
  if (!values) return unexpected(values.error());
  std::vector<bool> bits(values->size());
  std::transform(values->begin(), values->end(), bits.begin(), [](std::uint16_t value) { return value != 0; });
  return bits;
}

std::vector<BusRange> RegisterMap::live_read_runs(std::span<const RegisterEntry* const> entries) const {
  std::vector<BusRange> runs;
  for (std::size_t i = 0; i < entries.size();) {
    const std::uint16_t start = entries[i]->address;
    const auto count_to = [&](std::size_t j) { return static_cast<std::uint16_t>(entries[j]->address - start + 1); };
    std::size_t j = i + 1;
    while (j < entries.size() && count_to(j) <= modbus_limits::kReadRegisters &&
           plan_holding_read(start, count_to(j))) {
      ++j;
    }
    runs.push_back(BusRange{start, count_to(j - 1)});
    i = j;
  }
  return runs;
}

// --- writes ------------------------------------------------------------------------------------------

MapResult<WritePlan> RegisterMap::plan_register_write(std::uint16_t start,
                                                      std::span<const std::uint16_t> values) const {
  return plan_write(RequestSpace::HoldingRegisters, start, values);
}

MapResult<WritePlan> RegisterMap::plan_coil_write(std::uint16_t start, const std::vector<bool>& values) const {
  std::vector<std::uint16_t> registers(values.size());
  std::transform(values.begin(), values.end(), registers.begin(),
                 [](bool bit) -> std::uint16_t { return bit ? 1 : 0; });
  return plan_write(RequestSpace::Coils, start, registers);
}

std::optional<MapError> RegisterMap::unwritable(const RegisterEntry& entry) const {
  if (entry.counterpart == nullptr) {
    return MapError{ModbusException::IllegalDataAddress, field_label(*entry.shown) + " has no counterpart in table " +
                                                             std::string(servo_table_->name) + " (" + description_ +
                                                             ")"};
  }
  if (!entry.writable) {
    return MapError{ModbusException::IllegalDataAddress,
                    field_label(*entry.shown) + " of " + description_ + " is read-only" +
                        (entry.counterpart != entry.shown ? " (table " + std::string(servo_table_->name) + " field " +
                                                                std::string(entry.counterpart->name) + ")"
                                                          : "")};
  }
  return std::nullopt;
}

std::optional<MapError> RegisterMap::outside_range(const RegisterEntry& entry, std::int64_t value) const {
  if (value >= entry.min && value <= entry.max) return std::nullopt;
  return MapError{ModbusException::IllegalDataValue, "value " + std::to_string(value) + " for " +
                                                         field_label(*entry.shown) + " of " + description_ +
                                                         " is outside " + range_text(entry.min, entry.max)};
}

MapResult<CheckedWrite> RegisterMap::check_write(const RegisterEntry& entry, std::int64_t value) const {
  if (auto refused = unwritable(entry)) return unexpected(std::move(*refused));
  if (auto refused = outside_range(entry, value)) return unexpected(std::move(*refused));
  // In range, so it fits the register (entry ranges are int16 or uint16): its two's complement.
  const auto register_value = static_cast<std::uint16_t>(value);
  const auto converted = convert_write(entry, register_value);
  if (!converted) return unexpected(converted.error());
  return CheckedWrite{register_value, entry.counterpart};
}

MapResult<std::optional<RegisterMap::FieldWrite>> RegisterMap::convert_write(const RegisterEntry& entry,
                                                                             std::uint16_t register_value) const {
  const std::int32_t value = entry.min < 0 ? static_cast<std::int16_t>(register_value) : register_value;
  const std::string label = field_label(*entry.shown);
  if (auto refused = outside_range(entry, value)) return unexpected(std::move(*refused));
  const FieldSpec& field = *entry.counterpart;
  const std::string servo_label = "table " + std::string(servo_table_->name) + " field " + std::string(field.name) +
                                  " (" + address_text(*servo_table_, field.addr) + ")";
  std::int32_t field_value = value;
  const Conversion conversion = entry.link != nullptr ? entry.link->conversion : Conversion::Same;
  switch (conversion) {
    case Conversion::Same: break;
    case Conversion::Scale: field_value = scale_round(value, entry.link->scale_den, entry.link->scale_num); break;
    case Conversion::ValueMap: {
      const auto mapping = std::find_if(
          entry.link->values.begin(), entry.link->values.end(),
          [&](const ValueMapping& m) { return m.direction != MapDirection::ReadOnly && m.register_value == value; });
      if (mapping == entry.link->values.end()) {
        std::string accepted;
        for (const ValueMapping& m : entry.link->values) {
          if (m.direction != MapDirection::ReadOnly)
            accepted += (accepted.empty() ? "" : ", ") + std::to_string(m.register_value);
        }
        return bad_value("value " + std::to_string(value) + " for " + label + " has no counterpart in " + servo_label +
                         "; accepted: " + accepted);
      }
      field_value = mapping->field_value;
      break;
    }
    case Conversion::BaudRate: {
      const auto bps = baud_from_code(BusProtocol::ModbusRtu, static_cast<std::uint8_t>(value));
      const auto code =
          bps ? baud_code(servo_table_->protocol, *bps) : Expected<std::uint8_t>(unexpected(std::string()));
      if (!bps || !code) {
        return bad_value(
            "Modbus baud code " + std::to_string(value) + " for " + label + " (" +
            (bps ? std::to_string(*bps) + " bps" : std::string("no rate")) +
            "): the servo cannot run at that rate; its rates: " + valid_bauds_text(servo_table_->protocol));
      }
      field_value = *code;
      if (field_value > field.max) {
        return bad_value("Modbus baud code " + std::to_string(value) + " for " + label + " (" + std::to_string(*bps) +
                         " bps) is feetech code " + std::to_string(field_value) + ", which " + servo_label +
                         " does not take (codes " + range_text(field.min, field.max) + ")");
      }
      break;
    }
    case Conversion::FaultReset: {
      const std::uint16_t bits = register_value;
      if ((bits & ~kFaultResetAcceptedBits) != 0) {
        return bad_value("value " + protocol::hex_number(bits) + " for " + label + " sets undefined bits " +
                         protocol::hex_number(bits & ~kFaultResetAcceptedBits) +
                         "; bits 0 overload, 1 over-current, 2 set centre, 5 voltage, 6 overheat, 7 encoder");
      }
      if ((bits & kFaultResetSetCentre) == 0) return std::optional<FieldWrite>{};  // nothing to send
      field_value = kCalibrateTorqueValue;
      break;
    }
    case Conversion::StatusBits:
    case Conversion::BytePair: return bad_address(label + " of " + description_ + " is read-only");
  }
  const auto raw = encode_value(field, field_value);
  if (!raw) {
    std::string why = "outside " + range_text(field.min, field.max);
    if (!field.allowed_values.empty()) {
      why += " or not one of";
      for (const std::int32_t allowed : field.allowed_values) why += " " + std::to_string(allowed);
    }
    return bad_value("value " + std::to_string(value) + " for " + label +
                     (entry.link != nullptr ? " becomes " + std::to_string(field_value) + " in " + servo_label : "") +
                     ", " + why);
  }
  return std::optional<FieldWrite>{FieldWrite{&field, *raw, entry.address}};
}

MapResult<WritePlan> RegisterMap::plan_write(RequestSpace space, std::uint16_t start,
                                             std::span<const std::uint16_t> values) const {
  const bool bits = space == RequestSpace::Coils;
  const std::uint16_t limit = bits ? modbus_limits::kWriteBits : modbus_limits::kWriteRegisters;
  if (values.empty() || values.size() > limit) {  // the quantity first, 0x03, as for reads
    return bad_value("write of " + std::to_string(values.size()) + " " + std::string(space_name(space)) +
                     ": the quantity must be 1.." + std::to_string(limit));
  }
  const std::uint16_t table_end = end_address(*shown_table_);
  const bool staged = !bits && start >= kStagedWriteBase && table_end <= kStagedWriteBase;
  if (staged && !supports_staged_writes()) {
    return bad_address("staged writes (holding registers 512 + a) exist on packet buses only; " + description_ +
                       " is on a " + std::string(protocol::to_string(servo_table_->protocol)) + " bus");
  }
  const std::uint16_t base = staged ? static_cast<std::uint16_t>(start - kStagedWriteBase) : start;
  const std::uint32_t end = std::uint32_t{base} + values.size();
  if (end > table_end) {
    return bad_address(std::string(staged ? "staged write of " : "") + std::string(space_name(space)) + " " +
                       address_label(base) + ".." + address_label(end - 1) + " reach beyond " + description_ +
                       " (last address " + address_label(table_end - 1) + ")");
  }

  // Addresses first (0x02 before 0x03, as Modbus servers check them).
  struct Selected {
    const RegisterEntry* entry;
    std::uint16_t value;
  };
  std::vector<Selected> selected;
  for (std::size_t i = 0; i < values.size(); ++i) {
    const auto address = static_cast<std::uint16_t>(base + i);
    const RegisterEntry* entry = entry_covering(address);
    if (bits && (entry == nullptr || entry->address != address || !in_space(*entry, space))) {
      return bad_address("coil " + address_label(address) + " of " + description_ + " is not a coil" +
                         (entry != nullptr ? " (" + field_label(*entry->shown) + " is no boolean field)" : ""));
    }
    if (entry == nullptr) continue;  // a gap: its value is ignored
    if (entry->address != address) {
      if (entry->address >= base) continue;  // second byte, first byte written too: ignored
      return bad_address("address " + address_label(address) + " is the second byte of " + field_label(*entry->shown) +
                         " of " + description_ + "; write the field at its first address");
    }
    if (auto refused = unwritable(*entry)) return unexpected(std::move(*refused));
    selected.push_back(Selected{entry, values[i]});
  }
  if (selected.empty()) {
    return bad_address("write to " + address_label(base) + ".." + address_label(end - 1) + " of " + description_ +
                       " touches no field, only gaps or second bytes of two-byte fields");
  }

  std::vector<FieldWrite> writes;
  for (const Selected& item : selected) {
    const auto write = convert_write(*item.entry, item.value);
    if (!write) return unexpected(write.error());
    if (*write) writes.push_back(**write);
  }
  std::stable_sort(writes.begin(), writes.end(),
                   [](const FieldWrite& a, const FieldWrite& b) { return a.field->addr < b.field->addr; });
  for (std::size_t i = 1; i < writes.size(); ++i) {
    if (writes[i].field == writes[i - 1].field) {
      return bad_value(address_label(writes[i - 1].from_address) + " and " + address_label(writes[i].from_address) +
                       " of " + description_ + " both write table " + std::string(servo_table_->name) + " field " +
                       std::string(writes[i].field->name) + "; send them in two requests");
    }
  }

  WritePlan plan{.staged = staged, .writes = {}};
  const std::uint8_t unit_bytes = bytes_per_bus_address();
  for (const FieldWrite& write : writes) {
    const FieldSpec& field = *write.field;
    const bool continues =
        !plan.writes.empty() && plan.writes.back().address + plan.writes.back().data.size() / unit_bytes == field.addr;
    if (!continues) plan.writes.push_back(BusWrite{field.addr, {}});
    Bytes& data = plan.writes.back().data;
    data.resize(data.size() + field.size);
    store_raw(std::span<std::uint8_t>(data).last(field.size), field.size, byte_order_, write.raw);
  }
  if (staged && plan.writes.size() > 1) {
    std::string frames;
    for (const BusWrite& write : plan.writes) frames += (frames.empty() ? "" : ", ") + address_label(write.address);
    return bad_address(
        "a staged write must be one contiguous run of fields (the servo holds one REG WRITE until "
        "ACTION); this one needs frames at " +
        frames + " of " + description_);
  }
  return plan;
}

MapResult<Bytes> RegisterMap::field_bytes(const FieldSpec& servo_field, std::uint16_t register_value) const {
  // The field as this map shows it, so a sync group's value is checked as a write of it is.
  const RegisterEntry* entry = entry_at(servo_field.addr);
  if (entry == nullptr || entry->shown != &servo_field || entry->counterpart != &servo_field) {
    return bad_address("table " + std::string(servo_table_->name) + " field " + std::string(servo_field.name) +
                       " is not a register of " + description_ + " (sync groups use the native map)");
  }
  if (auto refused = unwritable(*entry)) return unexpected(std::move(*refused));
  const auto write = convert_write(*entry, register_value);
  if (!write) return unexpected(write.error());
  Bytes bytes(servo_field.size);
  store_raw(bytes, servo_field.size, byte_order_, (*write)->raw);  // a native field always has a value to write
  return bytes;
}

}  // namespace sms::modbus_map
