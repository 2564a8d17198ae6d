// libFuzzer target: sparkplug::decode, the parser of what arrives on the NCMD/DCMD topics from
// the broker (anyone allowed to publish there can send these bytes), and parse_host_state, the
// parser of the primary host's STATE topic. Checks: no crash, leak or UB; an accepted payload
// re-encodes to bytes that decode to the same payload and encode to the same bytes again
// (compared as bytes, so NaN values compare too); metrics without a datatype take the one their
// "birth" gives; an accepted STATE writes back to JSON that parses to the same state.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <span>
#include <string_view>

#include "protocol/sparkplug/sparkplug.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  namespace sp = sms::sparkplug;
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  if (const auto state = sp::parse_host_state(text)) {
    const auto again = sp::parse_host_state(sp::host_state_json(*state));
    if (!again || *again != *state) std::abort();
  }
  const auto born = sp::decode(std::span<const std::uint8_t>(data, size), [](std::string_view name) {
    return name.size() % 2 == 0 ? sp::DataType::Int16 : sp::DataType::Boolean;
  });
  if (born) {
    for (const auto& metric : born->metrics) {
      if (metric.type == sp::DataType::Unknown) std::abort();  // every name has a birth type here
    }
  }
  const auto payload = sms::sparkplug::decode(std::span<const std::uint8_t>(data, size));
  if (!payload) return 0;
  const auto bytes = sms::sparkplug::encode(*payload);
  const auto again = sms::sparkplug::decode(bytes);
  if (!again) std::abort();  // our own encoding must decode
  if (sms::sparkplug::encode(*again) != bytes) std::abort();
  for (const auto& metric : again->metrics) {
    if (metric.name.empty()) std::abort();  // refused on decoding
    (void)sms::sparkplug::integer_value(metric.value);
  }
  return 0;
}
