#pragma once
// The text of a committed document, which the modbus_map tests compare with the table data.
#include <fstream>
#include <sstream>
#include <string>

namespace sms::modbus_map::testing {

inline std::string read_file(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  std::ostringstream text;
  text << file.rdbuf();
  return text.str();
}

}  // namespace sms::modbus_map::testing
