#pragma once
// What the console's pages show, as JSON, from the gateway's own state: the overview (buses,
// servos, safety, gateway facts) and one servo's control table with its polled values. Reads
// only what /metrics and FC04 read (atomics, the poll cache under its short lock): never the bus.
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "config/config.h"
#include "gateway/observability/metrics.h"
#include "gateway/units/unit_router.h"

namespace sms::gateway::console {

// The poll block of one servo unit, decoded into its fields as FC04 shows them.
struct PolledValues {
  bool online = false;
  bool has_data = false;
  SteadyClock::time_point updated;  // when the bus thread stored the block
  std::uint8_t status = 0;
  std::vector<std::pair<const modbus_map::RegisterEntry*, std::int32_t>> values;  // ascending address
  std::optional<std::int32_t> value_of(std::string_view field) const;
};
// nullopt only when the unit has no poll block the map can show.
std::optional<PolledValues> read_polled(const ServoUnit& unit);
// Whether the register of `entry` is signed as a client sees it (negative minimum).
std::int32_t register_to_value(const modbus_map::RegisterEntry& entry, std::uint16_t reg);

// How the pages show a field's values: raw × scale, in `symbol`, with `decimals` places, as
// modbus_map::field_unit() reads the table's unit (the tag lists read it the same way).
// nullopt: no unit, or one that is no plain scale ("0.732 rpm or step/s" depends on the servo's
// phase): the pages show the raw value and the table's text.
struct UnitScale {
  double scale = 1;
  std::string symbol;
  int decimals = 0;
};
std::optional<UnitScale> unit_scale(const modbus_map::FieldSpec& field);
// {"scale": 0.1, "symbol": "V", "decimals": 1}, or null when unit_scale() has none.
nlohmann::json unit_scale_json(const modbus_map::FieldSpec& field);

// The entry of a shown field by name, or nullptr.
const modbus_map::RegisterEntry* entry_named(const modbus_map::RegisterMap& map, std::string_view field);
// The entry whose servo field is `servo_field` (motion spec names), or nullptr.
const modbus_map::RegisterEntry* entry_for_servo_field(const modbus_map::RegisterMap& map,
                                                       std::string_view servo_field);
// Fields only the Commissioning tools change (the servo leaves the bus when they change).
bool commissioning_only(std::string_view field);

// The overview page's data.
nlohmann::json overview_json(const config::Config& config, const MetricsSnapshot& metrics, const UnitRouter& units);
// One servo unit's control table (every field with address, unit, range, area, access).
nlohmann::json servo_description_json(const config::Config& config, const ServoUnit& unit);
// The wire time of one poll cycle of `bus` at its baud (the floor the cycle can reach), µs.
std::uint64_t poll_wire_floor_us(const config::Config& config, std::size_t bus_index, const UnitRouter& units);
// Microseconds on the steady clock (CLOCK_MONOTONIC): the time stamps the pages and the benchmark compare.
std::int64_t steady_us(SteadyClock::time_point when);

}  // namespace sms::gateway::console
