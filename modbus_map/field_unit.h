#pragma once
// A field's unit string as a scale and a symbol: "0.1 V" -> {0.1, "V"}, "0.087°" -> {0.087, "°"},
// "steps" -> {1, "steps"}, "" -> {1, ""}. The tag lists (sms-gateway tags) and the console show
// engineering values with it: value = register value × scale, in `symbol`. One parser, so every
// way of showing a field agrees.
#include <string_view>

#include "modbus_map/control_table.h"

namespace sms::modbus_map {

struct FieldUnit {
  double scale = 1.0;       // engineering value per register count
  std::string_view symbol;  // what is left of the unit string, trimmed; views the table's string
};

// The unit string's leading decimal number (digits, at most one '.') is the scale; a string that
// does not start with a digit has scale 1 and is all symbol. A leading number that is the whole
// string has an empty symbol.
FieldUnit parse_field_unit(std::string_view unit);
FieldUnit field_unit(const FieldSpec& field);

}  // namespace sms::modbus_map
