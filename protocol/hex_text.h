#pragma once
// Bytes and numbers as hex text, the way every log line, error and document of the project
// writes them.
#include <cstdint>
#include <span>
#include <string>

namespace sms::protocol {

// "FF FF 01 04": two upper-case digits a byte, a space between.
std::string hex_bytes(std::span<const std::uint8_t> bytes);
// "0x0A", "0x1F4": upper-case digits, at least two.
std::string hex_number(std::uint32_t value);

}  // namespace sms::protocol
