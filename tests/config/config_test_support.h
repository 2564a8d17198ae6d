#pragma once
// What the configuration tests share: a loader that returns the error text, and the smallest
// bus and servo a section's test can be appended to.
#include <string>
#include <string_view>

#include "config/load.h"

namespace sms::config::testing {

// The error of loading `yaml` as "plant.yaml" ("plant.yaml:3:5: ..."), or "<loaded>".
inline std::string error_text(std::string_view yaml) {
  const auto config = load_config_string(yaml, "plant.yaml");
  if (config) return "<loaded>";
  return config.error().to_string();
}

// One feetech bus with one sts servo: the rest of a configuration a section's test needs.
inline const std::string kBusAndServo = R"(buses:
  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1000000}
servos:
  - {bus: arm, id: 1, table: sts}
)";

}  // namespace sms::config::testing
