#include "protocol/hex_text.h"

namespace sms::protocol {
namespace {
constexpr char kDigits[] = "0123456789ABCDEF";
}  // namespace

std::string hex_bytes(std::span<const std::uint8_t> bytes) {
  std::string text;
  text.reserve(bytes.size() * 3);
  for (const auto byte : bytes) {
    if (!text.empty()) text += ' ';
    text += kDigits[byte >> 4];
    text += kDigits[byte & 0xF];
  }
  return text;
}

std::string hex_number(std::uint32_t value) {
  std::string digits;
  do {
    digits.insert(digits.begin(), kDigits[value & 0xF]);
    value >>= 4;
  } while (value != 0);
  if (digits.size() < 2) digits.insert(digits.begin(), '0');
  return "0x" + digits;
}

}  // namespace sms::protocol
