#include "config/secret_files.h"

#include <grp.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>

namespace sms::config {

namespace {

// The group the file should belong to: the package's service account where it exists (the
// gateway runs as it; `sudo sms-gateway --check-config` must not suggest root's own group), else
// this process's.
std::string group_name() {
  if (const group* service = getgrnam("_sms-gateway"); service != nullptr) return service->gr_name;
  if (const group* entry = getgrgid(getegid()); entry != nullptr && entry->gr_name != nullptr) return entry->gr_name;
  return std::to_string(getegid());
}

// The warning for `path` (what it holds: `what`), or empty when others can neither read nor change it.
std::string warning_for(const std::string& path, const std::string& what) {
  struct stat status {};
  if (path.empty() || ::stat(path.c_str(), &status) != 0) return {};
  const unsigned mode = status.st_mode & 07777;
  if ((mode & 0006) == 0) return {};
  char octal[8];
  std::snprintf(octal, sizeof octal, "%04o", mode);
  std::string how;
  if ((mode & 0004) != 0) how = "readable";
  if ((mode & 0002) != 0) how += std::string(how.empty() ? "" : " and ") + "writable";
  return what + " and is " + how + " by every user of this machine (mode " + octal + "): chmod 0640 " + path +
         " && chown root:" + group_name() + " " + path;
}

}  // namespace

std::vector<std::string> secret_file_warnings(const Config& config, const std::string& config_path) {
  std::vector<std::string> warnings;
  const auto add = [&](const std::string& path, const std::string& what) {
    if (auto warning = warning_for(path, what); !warning.empty()) warnings.push_back(std::move(warning));
  };
  if (config.console && !config.console->users.empty()) {
    add(config_path, "configuration file " + config_path + " holds console password hashes (console.users)");
  }
  if (config.console && !config.console->key.empty()) {
    add(config.console->key, "console.key " + config.console->key + " is a private key");
  }
  if (config.modbus_tcp.tls) {
    add(config.modbus_tcp.tls->private_key,
        "modbus_tcp.tls.private_key " + config.modbus_tcp.tls->private_key + " is a private key");
  }
  if (config.mqtt && config.mqtt->tls && !config.mqtt->tls->private_key.empty()) {
    add(config.mqtt->tls->private_key, "mqtt.tls.private_key " + config.mqtt->tls->private_key + " is a private key");
  }
  if (config.mqtt && !config.mqtt->password_file.empty()) {
    add(config.mqtt->password_file, "mqtt.password_file " + config.mqtt->password_file + " holds a password");
  }
  return warnings;
}

}  // namespace sms::config
