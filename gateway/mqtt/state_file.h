#pragma once
// A small state file that must survive a restart (config/README.md "state_dir"): here the
// Sparkplug bdSeq. Written atomically: a temporary file beside it, fsync, rename, fsync of the
// directory, so after a crash the file holds the old or the new text, never a torn one.
#include <optional>
#include <string>

#include "config/config.h"

namespace sms::gateway {

// The directory state files go to: `state_dir`, else $STATE_DIRECTORY (systemd; the first of a
// colon-separated list), else empty (nothing is kept).
std::string resolve_state_dir(const config::Config& config);

// Replaces `path`'s content with `text`. Returns the error (what failed, on which file) or empty.
std::string write_state_file(const std::string& path, const std::string& text);
// The file's content; nullopt when it does not exist. Throws std::runtime_error when it exists
// but cannot be read.
std::optional<std::string> read_state_file(const std::string& path);

}  // namespace sms::gateway
