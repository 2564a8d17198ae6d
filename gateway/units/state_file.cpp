#include "gateway/units/state_file.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <utility>

namespace sms::gateway {
namespace {

std::string errno_text(const std::string& what, const std::string& path) {
  return what + " " + path + ": " + std::strerror(errno);
}

class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }
  int release() { return std::exchange(fd_, -1); }

 private:
  int fd_;
};

}  // namespace

Expected<Ok> write_file_atomically(const std::string& path, std::string_view text) {
  const std::string temporary = path + ".new";
  Fd file(::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644));
  if (file.get() < 0) return unexpected(errno_text("cannot create", temporary));
  for (std::size_t written = 0; written < text.size();) {
    const ssize_t n = ::write(file.get(), text.data() + written, text.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      return unexpected(errno_text("cannot write", temporary));
    }
    written += static_cast<std::size_t>(n);
  }
  if (::fsync(file.get()) != 0) return unexpected(errno_text("cannot sync", temporary));
  if (::close(file.release()) != 0) return unexpected(errno_text("cannot close", temporary));
  if (::rename(temporary.c_str(), path.c_str()) != 0) return unexpected(errno_text("cannot rename it to", path));
  // The rename itself is durable only once the directory is.
  const std::string dir = std::filesystem::path(path).parent_path().string();
  Fd directory(::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (directory.get() >= 0) ::fsync(directory.get());
  return Ok{};
}

Expected<std::optional<std::string>> read_state_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    if (errno == ENOENT) return std::optional<std::string>();
    return unexpected(errno_text("cannot read", path));
  }
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) return unexpected(errno_text("cannot read", path));
  return std::optional<std::string>(text.str());
}

std::string check_state_dir(const std::string& dir) {
  struct stat info {};
  if (::stat(dir.c_str(), &info) != 0 && errno == ENOENT && ::mkdir(dir.c_str(), 0750) == 0) {
    return {};  // made here, by and for this user
  }
  if (::stat(dir.c_str(), &info) != 0) {
    return "state_dir " + dir + ": " + std::strerror(errno) +
           "; create it, writable by the gateway's user (the package's unit has StateDirectory=sms-gateway)";
  }
  if (!S_ISDIR(info.st_mode)) return "state_dir " + dir + " is not a directory";
  if (::access(dir.c_str(), W_OK | X_OK) != 0) {
    return "state_dir " + dir + " is not writable by this user (" + std::strerror(errno) +
           "); give the gateway's user write access";
  }
  return {};
}

}  // namespace sms::gateway
