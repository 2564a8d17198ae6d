// libFuzzer target: the YAML configuration loader (config/load.h) — the one input the gateway
// takes from a file an integrator edits by hand. The whole input is the file's text.
//
// Invariants:
//   - the loader never throws and never crashes, whatever the text (yaml-cpp's exceptions
//     must be turned into ConfigErrors);
//   - a rejection names the source, says something, and points at a line inside the text;
//   - an accepted configuration survives dump_config: the dump loads, to an equal Config,
//     and dumps again to the same text.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "config/load.h"
#include "fuzz_support.h"

namespace {

constexpr std::string_view kSource = "<fuzz>";

void check_rejection(std::string_view text, const sms::config::ConfigError& error) {
  SMS_FUZZ_CHECK(error.file == kSource, "error names source \"" + error.file + "\"");
  SMS_FUZZ_CHECK(!error.message.empty(), "error without a message");
  const auto lines = static_cast<std::uint32_t>(std::count(text.begin(), text.end(), '\n')) + 1;
  SMS_FUZZ_CHECK(error.line <= lines, "error at line " + std::to_string(error.line) + " of a " + std::to_string(lines) +
                                          "-line text: " + error.to_string());
  SMS_FUZZ_CHECK(error.to_string().starts_with(kSource), "to_string() does not start with the source");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const auto loaded = sms::config::load_config_string(text, kSource);
  if (!loaded) {
    check_rejection(text, loaded.error());
    return 0;
  }
  const std::string dump = sms::config::dump_config(*loaded);
  const auto reloaded = sms::config::load_config_string(dump, "<dump>");
  SMS_FUZZ_CHECK(reloaded.has_value(), "the dump of an accepted config does not load: " +
                                           (reloaded ? std::string() : reloaded.error().to_string()) + "\n" + dump);
  SMS_FUZZ_CHECK(*reloaded == *loaded, "the dump loads to a different Config:\n" + dump);
  SMS_FUZZ_CHECK(sms::config::dump_config(*reloaded) == dump, "dumping the reloaded Config changes the text:\n" + dump);
  return 0;
}
