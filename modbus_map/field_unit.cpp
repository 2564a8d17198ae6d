#include "modbus_map/field_unit.h"

#include <charconv>

namespace sms::modbus_map {
namespace {

bool is_digit(char c) { return c >= '0' && c <= '9'; }

std::string_view trimmed(std::string_view text) {
  while (!text.empty() && text.front() == ' ') text.remove_prefix(1);
  while (!text.empty() && text.back() == ' ') text.remove_suffix(1);
  return text;
}

}  // namespace

FieldUnit parse_field_unit(std::string_view unit) {
  unit = trimmed(unit);
  for (const std::string_view choice : {" or ", "/ ", "\u00d7"}) {
    if (unit.find(choice) != std::string_view::npos) return FieldUnit{1.0, unit, 0, false};
  }
  std::size_t end = 0;
  bool point = false;
  while (end < unit.size() && (is_digit(unit[end]) || (unit[end] == '.' && !point))) {
    point = point || unit[end] == '.';
    ++end;
  }
  // "10 ms" is a number; ".5" or a lone "." is not one the tables write.
  if (end == 0 || !is_digit(unit[0])) return FieldUnit{1.0, unit};
  double scale = 1.0;
  const auto [stop, error] = std::from_chars(unit.data(), unit.data() + end, scale);
  if (error != std::errc{} || stop != unit.data() + end || scale <= 0.0) return FieldUnit{1.0, unit};
  const std::string_view symbol = trimmed(unit.substr(end));
  if (symbol.empty()) return FieldUnit{1.0, unit, 0, false};
  const std::string_view number = unit.substr(0, end);
  const auto dot = number.find('.');
  const int decimals = dot == std::string_view::npos ? 0 : static_cast<int>(number.size() - dot - 1);
  return FieldUnit{scale, symbol, decimals, true};
}

FieldUnit field_unit(const FieldSpec& field) { return parse_field_unit(field.unit); }

}  // namespace sms::modbus_map
