// The start's warnings about secret files others may read (config/secret_files.h): the
// configuration holding console password hashes, and the private keys and password files the
// gateway loads, on real files with real modes.
#include "config/secret_files.h"

#include <grp.h>
#include <sys/stat.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>

namespace sms::config {
namespace {

class SecretFiles : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string pattern = (std::filesystem::temp_directory_path() / "sms-secret-files-XXXXXX").string();
    ASSERT_NE(mkdtemp(pattern.data()), nullptr);
    dir_ = pattern;
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::string file(const std::string& name, mode_t mode) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << "secret\n";
    EXPECT_EQ(::chmod(path.c_str(), mode), 0);
    return path;
  }
  static std::string group() {
    const struct group* entry = getgrgid(getegid());
    return entry != nullptr ? entry->gr_name : std::to_string(getegid());
  }

  std::filesystem::path dir_;
};

Config with_users() {
  Config config;
  config.console.emplace();
  config.console->users.push_back({"shift", Role::Operate, "$argon2id$v=19$..."});
  return config;
}

TEST_F(SecretFiles, AConfigurationWithHashesReadableByOthersIsNamed) {
  const Config config = with_users();
  const std::string path = file("cell.yaml", 0644);
  const auto warnings = secret_file_warnings(config, path);
  ASSERT_EQ(warnings.size(), 1u);
  EXPECT_EQ(warnings[0], "configuration file " + path +
                             " holds console password hashes (console.users) and is readable by every user of this "
                             "machine (mode 0644): chmod 0640 " +
                             path + " && chown root:" + group() + " " + path);
  EXPECT_TRUE(secret_file_warnings(config, file("closed.yaml", 0640)).empty()) << "the service group may read it";
  EXPECT_TRUE(secret_file_warnings(config, file("own.yaml", 0600)).empty());
  // Without users there is nothing secret in it.
  EXPECT_TRUE(secret_file_warnings(Config{}, path).empty());
  // --simulate: no file.
  EXPECT_TRUE(secret_file_warnings(config, "").empty());
}

TEST_F(SecretFiles, KeysAndPasswordFilesReadableOrWritableByOthersAreNamed) {
  Config config;
  config.console.emplace();
  config.console->certificate = file("console.crt", 0644);  // a certificate is public
  config.console->key = file("console.key", 0604);
  config.modbus_tcp.tls.emplace();
  config.modbus_tcp.tls->private_key = file("gateway.key", 0640);
  config.mqtt.emplace();
  config.mqtt->password_file = file("mqtt.password", 0662);
  config.mqtt->tls.emplace();
  config.mqtt->tls->private_key = file("client.key", 0644);
  const auto warnings = secret_file_warnings(config, file("cell.yaml", 0644));
  ASSERT_EQ(warnings.size(), 3u);
  EXPECT_EQ(warnings[0].rfind("console.key " + config.console->key +
                                  " is a private key and is readable by every user of this machine (mode 0604): chmod "
                                  "0640 " +
                                  config.console->key,
                              0),
            0u)
      << warnings[0];
  EXPECT_NE(warnings[1].find("mqtt.tls.private_key"), std::string::npos) << warnings[1];
  EXPECT_NE(warnings[2].find("mqtt.password_file " + config.mqtt->password_file +
                             " holds a password and is writable by every user of this machine (mode 0662)"),
            std::string::npos)
      << warnings[2];
}

TEST_F(SecretFiles, AMissingFileIsLeftToWhoeverLoadsIt) {
  Config config = with_users();
  config.console->key = (dir_ / "nosuch.key").string();
  EXPECT_TRUE(secret_file_warnings(config, (dir_ / "nosuch.yaml").string()).empty());
}

}  // namespace
}  // namespace sms::config
