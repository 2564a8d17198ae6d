// libFuzzer target: sparkplug::decode, the parser of what arrives on the NCMD/DCMD topics from
// the broker (anyone allowed to publish there can send these bytes). Checks: no crash, leak or
// UB; an accepted payload re-encodes to bytes that decode to the same payload and encode to the
// same bytes again (compared as bytes, so NaN values compare too).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <span>

#include "protocol/sparkplug/sparkplug.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
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
