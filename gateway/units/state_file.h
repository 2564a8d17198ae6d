#pragma once
// Small files that must survive a crash or a restart (config/README.md "state_dir"): written
// whole or not at all (a temporary file, fsync, rename, fsync of the directory), so a power cut
// mid-write leaves the old content or the new one, never a mix.
#include <optional>
#include <string>
#include <string_view>

#include "protocol/expected.h"

namespace sms::gateway {

// Replaces `path` with `text`. The error says what failed, with the path and the errno text.
Expected<Ok> write_file_atomically(const std::string& path, std::string_view text);
// The file's content; nullopt when it does not exist; an error when it cannot be read.
Expected<std::optional<std::string>> read_state_file(const std::string& path);
// Empty when `dir` is a directory this process can create files in (made here when it is missing
// and its parent exists); else what is wrong and what to do.
std::string check_state_dir(const std::string& dir);

}  // namespace sms::gateway
