#pragma once
// Files of the configuration that hold secrets, and whether every user of the machine may read
// them (docs/SECURITY.md "Files with secrets"): the configuration file itself when it holds
// console password hashes, and each private key or password file the gateway loads. The gateway
// logs one warning a file at start; it starts anyway (the file is the administrator's).
#include <string>
#include <vector>

#include "config/config.h"

namespace sms::config {

// One line per file that others may read or change (mode & 0006), naming the file, its mode and
// the chmod/chown to run, e.g. "configuration file /etc/sms-gateway/config.yaml holds console
// password hashes (console.users) and is readable by every user of this machine (mode 0644):
// chmod 0640 /etc/sms-gateway/config.yaml && chown root:_sms-gateway /etc/sms-gateway/config.yaml".
// `config_path` empty: the configuration is not a file (--simulate). A file that cannot be
// looked at is left to whoever loads it. The group named is the one the gateway runs as.
std::vector<std::string> secret_file_warnings(const Config& config, const std::string& config_path);

}  // namespace sms::config
