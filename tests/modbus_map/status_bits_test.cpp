// The status bits of every table (TableSpec::status_bits) against the notes of the table's own
// status field, and what status_faults makes of a status byte (docs/PROTOCOL.md §1.1, §1.2, §2.3).
// The simulator's side: tests/simulator/vendor_fidelity_test.cpp.
#include "modbus_map/status_bits.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cctype>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

using Strings = std::vector<std::string>;

// "bit0 voltage, 1 angle sensor, 2 over-temperature, 5 overload" -> {0: "voltage", 1: "angle sensor", ...}
std::map<int, std::string> bits_in_notes(std::string_view notes) {
  std::map<int, std::string> bits;
  std::string text(notes.substr(0, notes.find(';')));
  std::size_t at = 0;
  while (at < text.size()) {
    const std::size_t end = std::min(text.find(", ", at), text.size());
    std::string item = text.substr(at, end - at);
    if (item.starts_with("bit")) item.erase(0, 3);
    const std::size_t space = item.find(' ');
    if (space != std::string::npos && space > 0 && std::isdigit(static_cast<unsigned char>(item[0])) != 0) {
      bits[std::stoi(item.substr(0, space))] = item.substr(space + 1);
    }
    at = end + 2;
  }
  return bits;
}

// The notes' words and a bit's name mean the same bit when they agree but for case, spaces and an
// "over" prefix: "angle sensor" and angle_sensor, "over-temperature" and temperature, "load" and
// overload.
std::string meaning(std::string_view words) {
  std::string text;
  for (const char c : words) text += (c == ' ' || c == '-') ? '_' : static_cast<char>(std::tolower(c));
  if (text.starts_with("over_")) return text.substr(5);
  if (text.starts_with("over")) return text.substr(4);
  return text;
}

// Where the status byte is also a field of the table, the vendor's words are in its notes; d55d's
// is only the ERROR byte of its answers (checked against the simulator).
TEST(StatusBits, EveryTableNamesTheBitsItsStatusFieldsNotesName) {
  for (const TableSpec* table_spec : all_tables()) {
    const TableSpec& spec = *table_spec;
    if (spec.status_field.empty()) continue;
    const FieldSpec* field = field_by_name(spec, spec.status_field);
    ASSERT_NE(field, nullptr) << spec.name << "." << spec.status_field;
    const auto noted = bits_in_notes(field->notes);
    ASSERT_FALSE(noted.empty()) << spec.name << ": no bits in the notes '" << field->notes << "'";
    std::map<int, std::string> named;
    for (const StatusBit& bit : spec.status_bits) named[std::countr_zero(bit.mask)] = std::string(bit.name);
    Strings noted_meanings;
    Strings named_meanings;
    for (const auto& [number, words] : noted) noted_meanings.push_back(std::to_string(number) + " " + meaning(words));
    for (const auto& [number, name] : named) named_meanings.push_back(std::to_string(number) + " " + meaning(name));
    EXPECT_EQ(named_meanings, noted_meanings)
        << spec.name << "." << spec.status_field << ": notes '" << field->notes << "'";
  }
}

TEST(StatusBits, EveryTableHasItsOwnList) {
  EXPECT_TRUE(table(TableId::D55d).status_field.empty());
  for (const TableSpec* spec : all_tables()) {
    EXPECT_FALSE(status_bits(spec->id).empty()) << spec->name;
    EXPECT_EQ(status_bits(spec->id).data(), spec->status_bits.data()) << spec->name << ": one list, the table's";
  }
}

TEST(StatusBits, SmsmbsStatusRegisterIsNotItsFaultResetLayout) {
  // Register 0x100: bit0 voltage, 1 encoder, 2 temperature, 3 current, 4 torque on, 5 load.
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x01), Strings{"voltage"});
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x02), Strings{"encoder"});
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x04), Strings{"temperature"});
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x08), Strings{"current"});
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x20), Strings{"overload"});
  EXPECT_TRUE(status_faults(TableId::Smsmb, 0x10).empty()) << "torque on is no fault";
  EXPECT_EQ(status_faults(TableId::Smsmb, 0x11), Strings{"voltage"});
  EXPECT_EQ(status_faults(TableId::Smsmb, 0xC0), Strings{"bits 0xc0"});
}

TEST(StatusBits, FeetechTablesDifferInBitFour) {
  EXPECT_EQ(status_faults(TableId::Sts, 0x10), Strings{"angle"});
  EXPECT_EQ(status_faults(TableId::Sms1, 0x10), Strings{"bits 0x10"});
  EXPECT_EQ(status_faults(TableId::Scs, 0x21), (Strings{"voltage", "overload"}));
  EXPECT_EQ(status_faults(TableId::D55d, 0x41), (Strings{"over_temperature", "stall"}));
  EXPECT_TRUE(status_faults(TableId::D55d, 0).empty());
}

}  // namespace
}  // namespace sms::modbus_map
