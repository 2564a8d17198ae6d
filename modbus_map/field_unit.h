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
  int decimals = 0;         // places the scale has ("0.1 V": 1), for showing scaled values
  // One scale in one unit. Not so for a choice or a product ("0.732 rpm or step/s" depends on the
  // servo's phase, "deg × resolution", "ms / 0.1 %"), nor for a bare number: then scale is 1 and
  // symbol the whole text, and values are shown raw with that text.
  bool plain = true;
};

// The unit string's leading decimal number (digits, at most one '.') is the scale; a string that
// does not start with a digit has scale 1 and is all symbol.
FieldUnit parse_field_unit(std::string_view unit);
FieldUnit field_unit(const FieldSpec& field);

}  // namespace sms::modbus_map
