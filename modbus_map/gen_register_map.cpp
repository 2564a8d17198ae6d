// gen-register-map: prints the register map (docs/REGISTER_MAP.md) generated from the tables.
//   gen-register-map                 -> stdout
//   gen-register-map <output-file>   -> writes the file
#include <fstream>
#include <iostream>
#include <string>

#include "modbus_map/register_map_doc.h"

int main(int argc, char** argv) {
  if (argc > 2) {
    std::cerr << "usage: gen-register-map [output-file]\n";
    return 2;
  }
  const std::string markdown = sms::modbus_map::register_map_markdown();
  if (argc == 1) {
    std::cout << markdown;
    return std::cout ? 0 : 1;
  }
  std::ofstream file(argv[1], std::ios::binary | std::ios::trunc);
  file << markdown;
  if (!file) {
    std::cerr << "gen-register-map: cannot write " << argv[1] << "\n";
    return 1;
  }
  return 0;
}
