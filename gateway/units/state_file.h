#pragma once
// Small files that must survive a crash or a restart (config/README.md "state_dir"): written
// whole or not at all (a temporary file, fsync, rename, fsync of the directory), so a power cut
// mid-write leaves the old content or the new one, never a mix.
//
// And the one such file with a schema of its own, `<state_dir>/safety.state` (docs/SAFETY.md
// "What survives a restart"): the e-stop latch, the tripped watchdogs and the owed safe stops.
// Read strictly: anything that is not a complete state of the exact schema is refused with the
// reason, and the safety supervisor latches the e-stop on it.
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/expected.h"

namespace sms::gateway {

// Replaces `path` with `text`. The error says what failed, with the path and the errno text.
Expected<Ok> write_file_atomically(const std::string& path, std::string_view text);
// The file's content; nullopt when it does not exist; an error when it cannot be read or is not
// a regular file (a directory, a device).
Expected<std::optional<std::string>> read_state_file(const std::string& path);
// Empty when `dir` is a directory this process can create files in (made here when it is missing
// and its parent exists); else what is wrong and what to do.
std::string check_state_dir(const std::string& dir);

// --- safety.state -------------------------------------------------------------------------------
// A safe stop owed to a servo (BusEngine::owe_stop), as kept across a restart: the stop itself
// (the servo's torque off) follows from the servo's table in the configuration.
struct OwedStopRecord {
  std::string bus;
  std::uint8_t servo = 0;
  std::string why;             // what the stop was for ("e-stop", "watchdog", ...)
  bool answers_writes = true;  // false: only a read shows the stop taken (response level)
  bool operator==(const OwedStopRecord&) const = default;
};

struct SafetyStateRecord {
  bool estop_latched = false;
  std::vector<std::string> tripped_watchdogs;  // bus names
  std::vector<OwedStopRecord> owed_stops;
  bool operator==(const SafetyStateRecord&) const = default;
};

// The version written; 1 was the version-less file of two keys (estop_latched,
// tripped_watchdogs), still read.
inline constexpr int kSafetyStateVersion = 2;

// The file's text: a comment, then every key of version 2, one line each.
std::string render_safety_state(const SafetyStateRecord& state);
// The state `text` holds, or why it is not a complete state of the exact schema (empty, not
// YAML, more than one document, not a map, a key unknown, missing or repeated, a value of the
// wrong kind, a version this gateway does not read). Bus names are not checked against any
// configuration here: that is the caller's (a stale name is a warning, not damage).
Expected<SafetyStateRecord> parse_safety_state(std::string_view text);

}  // namespace sms::gateway
