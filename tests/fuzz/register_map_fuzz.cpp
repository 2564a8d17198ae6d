// libFuzzer target: modbus_map::RegisterMap planning (docs/PLC_GUIDE.md), which every Modbus request
// to a servo unit goes through before any bus traffic. The input is read front to back (zeros
// once it runs out), so a seed reads in a hex dump: TABLE PROFILE BYTE_ORDER (taken modulo 4,
// 2, 3), then requests until the input ends, OP taken modulo 7, numbers big-endian:
//   0 FC03, 1 FC04:  OP START(2) COUNT(1) HAS_POLL POLL_START(2) POLL_COUNT(1) REPLY BYTES...
//   2 FC01, 3 FC02:  the same with COUNT(2)
//   4 FC16:          OP START(2) COUNT(1) VALUES(2 each)
//   5 FC15:          OP START(2) COUNT(2) PACKED BITS
//   6 field_bytes:   OP FIELD_INDEX VALUE(2)
//
// Invariants:
//   - whatever the request, planning returns a plan or an address / value exception with a
//     message; never a crash, never another code;
//   - a read plan echoes the request, stays inside the bus address space (one range on packet
//     buses), and reads the poll cache only inside the poll block it was given;
//   - replies of exactly the planned sizes give exactly `count` values; a reply one byte short
//     is ServerDeviceFailure (0x04);
//   - a write plan's frames are in ascending, non-overlapping bus address order, each carrying
//     whole addresses; it is staged exactly when a register write starts at 512 or above;
//   - field_bytes gives exactly the field's size in bytes, or a value exception.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "fuzz_support.h"
#include "modbus_map/register_map.h"

namespace {

namespace mm = sms::modbus_map;
using sms::fuzz::hex;
using sms::protocol::Bytes;

class Reader {
 public:
  explicit Reader(std::span<const std::uint8_t> data) : data_(data) {}
  bool empty() const { return data_.empty(); }
  std::uint8_t u8() {
    if (data_.empty()) return 0;
    const std::uint8_t value = data_[0];
    data_ = data_.subspan(1);
    return value;
  }
  std::uint16_t u16() {
    const std::uint8_t high = u8();
    return static_cast<std::uint16_t>(high << 8 | u8());
  }
  bool flag() { return (u8() & 1) != 0; }
  Bytes bytes(std::size_t count) {
    Bytes out(count, 0);
    for (auto& byte : out) byte = u8();
    return out;
  }

 private:
  std::span<const std::uint8_t> data_;
};

std::string request_label(const char* function, std::uint16_t start, std::size_t count, const mm::RegisterMap& map) {
  return std::string(function) + " start " + std::to_string(start) + " count " + std::to_string(count) + " on " +
         map.description();
}

void check_planning_error(const mm::MapError& error, const std::string& request) {
  SMS_FUZZ_CHECK(
      error.code == mm::ModbusException::IllegalDataAddress || error.code == mm::ModbusException::IllegalDataValue,
      request + ": planning answered exception " + std::to_string(static_cast<int>(error.code)) + " (" + error.message +
          ")");
  SMS_FUZZ_CHECK(!error.message.empty(), request + ": exception without a message");
}

void check_read(Reader& input, const mm::RegisterMap& map, mm::RequestSpace space) {
  const std::uint16_t start = input.u16();
  const bool bits = space == mm::RequestSpace::Coils || space == mm::RequestSpace::DiscreteInputs;
  const std::uint16_t count = bits ? input.u16() % 2002 : input.u8();
  const bool have_poll_block = input.flag();
  const std::uint16_t poll_start = input.u16();
  const mm::BusRange poll_block{poll_start, input.u8()};

  const char* function = bits ? (space == mm::RequestSpace::Coils ? "FC01" : "FC02")
                              : (space == mm::RequestSpace::HoldingRegisters ? "FC03" : "FC04");
  const auto plan = [&]() -> mm::MapResult<mm::ReadPlan> {
    switch (space) {
      case mm::RequestSpace::HoldingRegisters: return map.plan_holding_read(start, count);
      case mm::RequestSpace::InputRegisters: return map.plan_input_read(start, count, poll_block);
      case mm::RequestSpace::Coils: return map.plan_coil_read(start, count);
      case mm::RequestSpace::DiscreteInputs: break;
    }
    return map.plan_discrete_read(start, count, have_poll_block ? std::optional(poll_block) : std::nullopt);
  }();
  const std::string request = request_label(function, start, count, map);
  if (!plan) {
    check_planning_error(plan.error(), request);
    return;
  }

  SMS_FUZZ_CHECK(plan->space == space && plan->start == start && plan->count == count,
                 request + ": plan does not echo the request");
  SMS_FUZZ_CHECK(count >= 1 && count <= (bits ? mm::modbus_limits::kReadBits : mm::modbus_limits::kReadRegisters),
                 request + ": planned a count outside the Modbus limits");
  const bool packet_bus = map.servo_table().addressing == mm::Addressing::Byte;
  SMS_FUZZ_CHECK(!packet_bus || plan->reads.size() <= 1, request + ": more than one READ on a packet bus");
  for (const mm::BusRange& range : plan->reads) {
    SMS_FUZZ_CHECK(range.count >= 1 && range.end() <= 0x10000, request + ": empty or wrapping bus range");
    if (plan->source == mm::ReadSource::PollCache) {
      SMS_FUZZ_CHECK(space == mm::RequestSpace::InputRegisters || space == mm::RequestSpace::DiscreteInputs,
                     request + ": a live space planned from the poll cache");
      SMS_FUZZ_CHECK(space != mm::RequestSpace::DiscreteInputs || have_poll_block,
                     request + ": poll cache planned without a poll block");
      SMS_FUZZ_CHECK(poll_block.contains(range), request + ": poll-cache range outside the poll block");
    }
  }

  // Replies of exactly the planned sizes, with whatever bytes the servo had.
  std::vector<Bytes> replies;
  for (const mm::BusRange& range : plan->reads) {
    const std::size_t size = std::size_t{range.count} * map.bytes_per_bus_address();
    replies.push_back(input.bytes(size));
  }
  if (bits) {
    const auto values = map.bits_from(*plan, replies);
    SMS_FUZZ_CHECK(values.has_value(),
                   request + ": whole replies refused: " + (values ? std::string() : values.error().message));
    SMS_FUZZ_CHECK(values->size() == count, request + ": " + std::to_string(values->size()) + " bits answered");
  } else {
    const auto values = map.registers_from(*plan, replies);
    SMS_FUZZ_CHECK(values.has_value(),
                   request + ": whole replies refused: " + (values ? std::string() : values.error().message));
    SMS_FUZZ_CHECK(values->size() == count, request + ": " + std::to_string(values->size()) + " registers answered");
  }

  if (!replies.empty()) {
    replies.back().pop_back();
    const bool refused = bits ? !map.bits_from(*plan, replies).has_value() : !map.registers_from(*plan, replies);
    SMS_FUZZ_CHECK(refused, request + ": a reply one byte short was accepted");
    const auto error = bits ? map.bits_from(*plan, replies).error() : map.registers_from(*plan, replies).error();
    SMS_FUZZ_CHECK(error.code == mm::ModbusException::ServerDeviceFailure,
                   request + ": short reply answered " + std::to_string(static_cast<int>(error.code)));
  }
}

void check_write_plan(const mm::RegisterMap& map, const mm::WritePlan& plan, bool expect_staged,
                      const std::string& request) {
  SMS_FUZZ_CHECK(plan.staged == expect_staged, request + (plan.staged ? ": staged" : ": not staged"));
  std::uint32_t previous_end = 0;
  for (const mm::BusWrite& write : plan.writes) {
    const std::size_t per_address = map.bytes_per_bus_address();
    SMS_FUZZ_CHECK(!write.data.empty() && write.data.size() % per_address == 0,
                   request + ": frame of " + std::to_string(write.data.size()) + " bytes");
    SMS_FUZZ_CHECK(write.data.size() <= sms::protocol::kMaxParams - 1,
                   request + ": frame larger than one WRITE can carry");
    const std::uint32_t end = write.address + static_cast<std::uint32_t>(write.data.size() / per_address);
    SMS_FUZZ_CHECK(write.address >= previous_end && end <= 0x10000,
                   request + ": frames overlap or are out of order at bus address " + std::to_string(write.address));
    previous_end = end;
  }
}

void check_register_write(Reader& input, const mm::RegisterMap& map) {
  const std::uint16_t start = input.u16();
  const std::size_t count = input.u8();
  std::vector<std::uint16_t> values;
  for (std::size_t i = 0; i < count; ++i) values.push_back(input.u16());
  const std::string request = request_label("FC16", start, count, map) + " values " +
                              hex(std::span(reinterpret_cast<const std::uint8_t*>(values.data()), values.size() * 2));
  const auto plan = map.plan_register_write(start, values);
  if (!plan) {
    check_planning_error(plan.error(), request);
    return;
  }
  SMS_FUZZ_CHECK(count >= 1 && count <= mm::modbus_limits::kWriteRegisters,
                 request + ": planned a count outside the Modbus limits");
  check_write_plan(map, *plan, start >= mm::kStagedWriteBase, request);
}

void check_coil_write(Reader& input, const mm::RegisterMap& map) {
  const std::uint16_t start = input.u16();
  const std::size_t count = input.u16() % 1970;
  std::vector<bool> values;
  std::uint8_t packed = 0;
  for (std::size_t i = 0; i < count; ++i) {
    if (i % 8 == 0) packed = input.u8();
    values.push_back(((packed >> (i % 8)) & 1) != 0);
  }
  const std::string request = request_label("FC15", start, count, map);
  const auto plan = map.plan_coil_write(start, values);
  if (!plan) {
    check_planning_error(plan.error(), request);
    return;
  }
  SMS_FUZZ_CHECK(count >= 1 && count <= mm::modbus_limits::kWriteBits,
                 request + ": planned a count outside the Modbus limits");
  check_write_plan(map, *plan, false, request);
}

void check_field_bytes(Reader& input, const mm::RegisterMap& map) {
  const auto fields = map.servo_table().fields;
  if (fields.empty()) return;
  const mm::FieldSpec& field = fields[input.u8() % fields.size()];
  const std::uint16_t value = input.u16();
  const std::string request =
      "field_bytes(" + std::string(field.name) + ", " + std::to_string(value) + ") on " + map.description();
  const auto bytes = map.field_bytes(field, value);
  if (!bytes) {
    check_planning_error(bytes.error(), request);
    return;
  }
  SMS_FUZZ_CHECK(bytes->size() == field.size, request + ": " + std::to_string(bytes->size()) + " bytes");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  Reader input(std::span<const std::uint8_t>(data, size));
  const auto table = static_cast<mm::TableId>(input.u8() % 4);
  const auto profile = input.flag() ? mm::Profile::Smsmb : mm::Profile::Native;
  std::optional<mm::ByteOrder> byte_order;
  switch (input.u8() % 3) {
    case 1: byte_order = mm::ByteOrder::LowFirst; break;
    case 2: byte_order = mm::ByteOrder::HighFirst; break;
    default: break;
  }
  const auto map = mm::RegisterMap::create(table, profile, byte_order);
  if (!map) {
    // Only the combinations register_map.h rules out may fail: the smsmb profile of a table
    // that is not a feetech packet table, or a byte order forced on the SMSMB registers.
    const bool feetech_table = table == mm::TableId::Sts || table == mm::TableId::Sms1;
    SMS_FUZZ_CHECK((profile == mm::Profile::Smsmb && !feetech_table) || (table == mm::TableId::Smsmb && byte_order),
                   "RegisterMap::create refused table " + std::to_string(static_cast<int>(table)) + " profile " +
                       std::string(mm::to_string(profile)) + ": " + map.error());
    return 0;
  }
  while (!input.empty()) {
    switch (input.u8() % 7) {
      case 0: check_read(input, *map, mm::RequestSpace::HoldingRegisters); break;
      case 1: check_read(input, *map, mm::RequestSpace::InputRegisters); break;
      case 2: check_read(input, *map, mm::RequestSpace::Coils); break;
      case 3: check_read(input, *map, mm::RequestSpace::DiscreteInputs); break;
      case 4: check_register_write(input, *map); break;
      case 5: check_coil_write(input, *map); break;
      default: check_field_bytes(input, *map); break;
    }
  }
  return 0;
}
