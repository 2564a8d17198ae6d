#include "gateway/mqtt/state_file.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace sms::gateway {
namespace {

std::string errno_text() { return std::strerror(errno); }

// Writes all of `text` to `fd`; false (errno set) on failure.
bool write_all(int fd, const std::string& text) {
  std::size_t done = 0;
  while (done < text.size()) {
    const ssize_t n = ::write(fd, text.data() + done, text.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    done += static_cast<std::size_t>(n);
  }
  return true;
}

}  // namespace

std::string resolve_state_dir(const config::Config& config) {
  if (!config.state_dir.empty()) return config.state_dir;
  const char* systemd = std::getenv("STATE_DIRECTORY");
  if (systemd == nullptr) return {};
  const std::string dirs = systemd;
  return dirs.substr(0, dirs.find(':'));
}

std::string write_state_file(const std::string& path, const std::string& text) {
  const std::filesystem::path target(path);
  std::error_code error;
  std::filesystem::create_directories(target.parent_path(), error);
  if (error) return "cannot create " + target.parent_path().string() + ": " + error.message();
  const std::string temporary = path + ".tmp";
  const int fd = ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return "cannot write " + temporary + ": " + errno_text();
  if (!write_all(fd, text) || ::fsync(fd) != 0) {
    const std::string why = "cannot write " + temporary + ": " + errno_text();
    ::close(fd);
    ::unlink(temporary.c_str());
    return why;
  }
  ::close(fd);
  if (::rename(temporary.c_str(), path.c_str()) != 0) {
    const std::string why = "cannot rename " + temporary + " to " + path + ": " + errno_text();
    ::unlink(temporary.c_str());
    return why;
  }
  // The rename itself is durable once the directory is synced.
  const std::string directory = target.parent_path().empty() ? "." : target.parent_path().string();
  if (const int dir = ::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC); dir >= 0) {
    ::fsync(dir);
    ::close(dir);
  }
  return {};
}

std::optional<std::string> read_state_file(const std::string& path) {
  std::error_code error;
  if (!std::filesystem::exists(path, error)) {
    if (error) throw std::runtime_error("cannot look at " + path + ": " + error.message());
    return std::nullopt;
  }
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot read " + path + " (check that the gateway may read it)");
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace sms::gateway
