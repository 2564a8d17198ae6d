#include "simulator/state_file.h"

#include <cerrno>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <system_error>

namespace sms::simulator {

PersistedState load_state_file(const std::string& path) {
  PersistedState state;
  std::ifstream in(path);
  if (!in) return state;
  std::string line;
  std::size_t line_number = 0;
  while (std::getline(in, line)) {
    ++line_number;
    if (line.empty() || line[0] == '#') continue;
    const auto fail = [&](const std::string& why) {
      throw std::runtime_error(
          path + ":" + std::to_string(line_number) + ": " + why +
          " (expected `eeprom|backup SLOT TABLE name=value ...`; delete the file to start afresh)");
    };
    std::istringstream words(line);
    std::string kind;
    std::size_t slot = 0;
    std::string table;
    if (!(words >> kind >> slot >> table) || (kind != "eeprom" && kind != "backup")) fail("unreadable line");
    PersistedServo& servo = state[slot];
    if (!servo.table.empty() && servo.table != table) fail("slot " + std::to_string(slot) + " has two tables");
    servo.table = table;
    FieldValues& values = kind == "eeprom" ? servo.eeprom : servo.backup;
    std::string pair;
    while (words >> pair) {
      const auto equals = pair.find('=');
      if (equals == std::string::npos || equals == 0) fail("'" + pair + "' is not name=value");
      try {
        std::size_t used = 0;
        // stoull: with stoul, "-1" wrapped to 0xFFFFFFFF passed the range check where long has 32 bits.
        const unsigned long long value = std::stoull(pair.substr(equals + 1), &used, 0);
        if (used != pair.size() - equals - 1 || value > 0xFFFFFFFFULL) throw std::out_of_range(pair);
        values[pair.substr(0, equals)] = static_cast<std::uint32_t>(value);
      } catch (const std::logic_error&) {
        fail("'" + pair + "' has no valid number");
      }
    }
  }
  return state;
}

void save_state_file(const std::string& path, const PersistedState& state) {
  const std::string temporary = path + ".tmp";
  {
    std::ofstream out(temporary, std::ios::trunc);
    if (!out) throw std::system_error(errno, std::generic_category(), "cannot write state file " + temporary);
    out << "# sms-sim state: per servo slot, the EEPROM that survives a power cycle and the BACKUP image\n";
    for (const auto& [slot, servo] : state) {
      for (const auto& [kind, values] : {std::pair{"eeprom", &servo.eeprom}, std::pair{"backup", &servo.backup}}) {
        out << kind << ' ' << slot << ' ' << servo.table;
        for (const auto& [name, value] : *values) out << ' ' << name << '=' << value;
        out << '\n';
      }
    }
    out.flush();
    if (!out) throw std::system_error(errno, std::generic_category(), "cannot write state file " + temporary);
  }
  if (std::rename(temporary.c_str(), path.c_str()) != 0) {
    throw std::system_error(errno, std::generic_category(), "cannot replace state file " + path);
  }
}

}  // namespace sms::simulator
