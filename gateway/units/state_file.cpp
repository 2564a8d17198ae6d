#include "gateway/units/state_file.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <filesystem>
#include <map>
#include <span>
#include <utility>

#include <yaml-cpp/yaml.h>

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
  // A failed attempt leaves no half-written temporary behind (the next one truncates it anyway).
  const auto fail = [&temporary](const std::string& what) {
    const int saved = errno;
    ::unlink(temporary.c_str());
    errno = saved;
    return unexpected(errno_text(what, temporary));
  };
  Fd file(::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644));
  if (file.get() < 0) return unexpected(errno_text("cannot create", temporary));
  for (std::size_t written = 0; written < text.size();) {
    const ssize_t n = ::write(file.get(), text.data() + written, text.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      return fail("cannot write");
    }
    written += static_cast<std::size_t>(n);
  }
  if (::fsync(file.get()) != 0) return fail("cannot sync");
  if (::close(file.release()) != 0) return fail("cannot close");
  if (::rename(temporary.c_str(), path.c_str()) != 0) {
    const int saved = errno;
    ::unlink(temporary.c_str());
    errno = saved;
    return unexpected(errno_text("cannot rename " + temporary + " to", path));
  }
  // The rename itself is durable only once the directory is.
  const std::string dir = std::filesystem::path(path).parent_path().string();
  const std::string dir_name = dir.empty() ? "." : dir;
  Fd directory(::open(dir_name.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (directory.get() < 0) return unexpected(errno_text("cannot open the directory", dir_name));
  // EINVAL: a file system that cannot sync directories (the rename is as durable as it gets there).
  if (::fsync(directory.get()) != 0 && errno != EINVAL) return unexpected(errno_text("cannot sync", dir_name));
  return Ok{};
}

Expected<std::optional<std::string>> read_state_file(const std::string& path) {
  Fd file(::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOCTTY));
  if (file.get() < 0) {
    if (errno == ENOENT) return std::optional<std::string>();
    return unexpected(errno_text("cannot read", path));
  }
  struct stat info {};
  if (::fstat(file.get(), &info) != 0) return unexpected(errno_text("cannot read", path));
  if (!S_ISREG(info.st_mode)) {
    return unexpected(path + " is not a regular file (" + (S_ISDIR(info.st_mode) ? "a directory" : "a device or pipe") +
                      "); remove it");
  }
  std::string text;
  char buffer[4096];
  for (;;) {
    const ssize_t n = ::read(file.get(), buffer, sizeof buffer);
    if (n < 0) {
      if (errno == EINTR) continue;
      return unexpected(errno_text("cannot read", path));
    }
    if (n == 0) break;
    text.append(buffer, static_cast<std::size_t>(n));
  }
  return std::optional<std::string>(std::move(text));
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

// ==== safety.state ==============================================================================

namespace {

// The schema, as data: the keys of each map, every one required, no other allowed.
constexpr std::string_view kVersionKey = "version";
constexpr std::array<std::string_view, 4> kStateKeys{kVersionKey, "estop_latched", "tripped_watchdogs", "owed_stops"};
constexpr std::array<std::string_view, 2> kVersion1Keys{"estop_latched", "tripped_watchdogs"};
constexpr std::array<std::string_view, 4> kOwedStopKeys{"bus", "servo", "why", "answers_writes"};
constexpr unsigned kHighestServoId = 253;  // 254 is the broadcast ID, 255 none

using Problem = Unexpected<std::string>;

// A value as the log shows it: printable, and short (a damaged file may hold anything).
std::string shown(const std::string& text) {
  constexpr std::size_t kMost = 40;
  std::string out;
  for (const char c : text.substr(0, kMost)) out += (c >= ' ' && c <= '~') ? c : '?';
  return text.size() > kMost ? out + "..." : out;
}

std::string kind_of(const YAML::Node& node) {
  switch (node.Type()) {
    case YAML::NodeType::Null: return "empty";
    case YAML::NodeType::Scalar:
      return "`" + shown(node.Scalar()) + "`" + (node.Tag() == "?" ? "" : " (quoted or tagged)");
    case YAML::NodeType::Sequence: return "a list";
    case YAML::NodeType::Map: return "a map";
    case YAML::NodeType::Undefined: break;
  }
  return "undefined";
}

// A plain (unquoted, untagged) scalar: what the gateway writes for booleans and numbers.
bool plain_scalar(const YAML::Node& node) { return node.IsScalar() && node.Tag() == "?"; }

// The map's values by key when its keys are exactly `keys`; else what is wrong, at `where`.
Expected<std::map<std::string, YAML::Node>> exact_map(const YAML::Node& node, std::span<const std::string_view> keys,
                                                      const std::string& where) {
  if (!node.IsMap()) return Problem{where + " is " + kind_of(node) + ", not a map of its keys"};
  std::map<std::string, YAML::Node> values;
  for (const auto& entry : node) {
    if (!entry.first.IsScalar()) return Problem{where + " has a key that is " + kind_of(entry.first)};
    const std::string key = entry.first.Scalar();
    if (std::find(keys.begin(), keys.end(), key) == keys.end())
      return Problem{where + " has an unknown key `" + shown(key) + "`"};
    if (!values.emplace(key, entry.second).second) return Problem{where + " has the key `" + shown(key) + "` twice"};
  }
  for (const auto key : keys) {
    if (values.count(std::string(key)) == 0) return Problem{where + " misses the key `" + std::string(key) + "`"};
  }
  return values;
}

Expected<bool> read_bool(const YAML::Node& node, const std::string& where) {
  if (plain_scalar(node) && node.Scalar() == "true") return true;
  if (plain_scalar(node) && node.Scalar() == "false") return false;
  return Problem{where + " is " + kind_of(node) + ", not true or false"};
}

Expected<unsigned> read_unsigned(const YAML::Node& node, unsigned highest, const std::string& where) {
  unsigned value = 0;
  if (plain_scalar(node)) {
    const std::string& text = node.Scalar();
    const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (!text.empty() && error == std::errc() && end == text.data() + text.size() && value <= highest) return value;
  }
  return Problem{where + " is " + kind_of(node) + ", not a whole number from 0 to " + std::to_string(highest)};
}

Expected<std::string> read_name(const YAML::Node& node, const std::string& where) {
  if (node.IsScalar() && !node.Scalar().empty()) return node.Scalar();
  return Problem{where + " is " + kind_of(node) + ", not a name"};
}

Expected<std::vector<std::string>> read_names(const YAML::Node& node, const std::string& where) {
  if (!node.IsSequence()) return Problem{where + " is " + kind_of(node) + ", not a list of bus names"};
  std::vector<std::string> names;
  for (std::size_t i = 0; i < node.size(); ++i) {
    auto name = read_name(node[i], where + "[" + std::to_string(i) + "]");
    if (!name) return Problem{name.error()};
    names.push_back(std::move(*name));
  }
  return names;
}

Expected<std::vector<OwedStopRecord>> read_owed_stops(const YAML::Node& node, const std::string& where) {
  if (!node.IsSequence()) return Problem{where + " is " + kind_of(node) + ", not a list of owed stops"};
  std::vector<OwedStopRecord> stops;
  for (std::size_t i = 0; i < node.size(); ++i) {
    const std::string at = where + "[" + std::to_string(i) + "]";
    const auto keys = exact_map(node[i], kOwedStopKeys, at);
    if (!keys) return Problem{keys.error()};
    auto bus = read_name(keys->at("bus"), at + ".bus");
    if (!bus) return Problem{bus.error()};
    const auto servo = read_unsigned(keys->at("servo"), kHighestServoId, at + ".servo");
    if (!servo) return Problem{servo.error()};
    auto why = read_name(keys->at("why"), at + ".why");
    if (!why) return Problem{why.error()};
    const auto answers = read_bool(keys->at("answers_writes"), at + ".answers_writes");
    if (!answers) return Problem{answers.error()};
    stops.push_back(OwedStopRecord{std::move(*bus), static_cast<std::uint8_t>(*servo), std::move(*why), *answers});
  }
  return stops;
}

}  // namespace

std::string render_safety_state(const SafetyStateRecord& state) {
  YAML::Emitter out;
  out << YAML::Comment(
      "sms-gateway safety state, written by the gateway (docs/SAFETY.md \"What survives a restart\"). A latched "
      "e-stop, a tripped watchdog and an owed safe stop survive a restart; reset them over Modbus (gateway unit "
      "coils 1 and 2), not here: a file that is not exactly what the gateway writes latches the e-stop.");
  out << YAML::BeginMap;
  out << YAML::Key << std::string(kVersionKey) << YAML::Value << kSafetyStateVersion;
  out << YAML::Key << "estop_latched" << YAML::Value << state.estop_latched;
  out << YAML::Key << "tripped_watchdogs" << YAML::Value << YAML::Flow << YAML::BeginSeq;
  for (const auto& name : state.tripped_watchdogs) out << name;
  out << YAML::EndSeq;
  out << YAML::Key << "owed_stops" << YAML::Value << YAML::Flow << YAML::BeginSeq;
  for (const auto& stop : state.owed_stops) {
    out << YAML::BeginMap << YAML::Key << "bus" << YAML::Value << stop.bus << YAML::Key << "servo" << YAML::Value
        << static_cast<unsigned>(stop.servo) << YAML::Key << "why" << YAML::Value << stop.why << YAML::Key
        << "answers_writes" << YAML::Value << stop.answers_writes << YAML::EndMap;
  }
  out << YAML::EndSeq;
  out << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

Expected<SafetyStateRecord> parse_safety_state(std::string_view text) {
  std::vector<YAML::Node> documents;
  try {
    documents = YAML::LoadAll(std::string(text));
  } catch (const YAML::Exception& error) {
    return Problem{"it is not YAML (" + std::string(error.what()) + ")"};
  }
  if (documents.empty() || (documents.size() == 1 && documents[0].IsNull())) return Problem{"it is empty"};
  if (documents.size() != 1)
    return Problem{"it holds " + std::to_string(documents.size()) + " YAML documents, not one"};
  const YAML::Node& root = documents[0];
  // Version 1 had no version key and two keys; every later version names itself.
  const bool version1 = root.IsMap() && !root[std::string(kVersionKey)];
  const auto keys = version1 ? exact_map(root, kVersion1Keys, "it") : exact_map(root, kStateKeys, "it");
  if (!keys) return Problem{keys.error()};
  SafetyStateRecord state;
  if (!version1) {
    const YAML::Node& version = keys->at(std::string(kVersionKey));
    if (!plain_scalar(version) || version.Scalar() != std::to_string(kSafetyStateVersion)) {
      return Problem{"its version is " + kind_of(version) + "; this gateway reads version " +
                     std::to_string(kSafetyStateVersion) + " (and 1)"};
    }
  }
  const auto latched = read_bool(keys->at("estop_latched"), "estop_latched");
  if (!latched) return Problem{latched.error()};
  state.estop_latched = *latched;
  auto tripped = read_names(keys->at("tripped_watchdogs"), "tripped_watchdogs");
  if (!tripped) return Problem{tripped.error()};
  state.tripped_watchdogs = std::move(*tripped);
  if (!version1) {
    auto owed = read_owed_stops(keys->at("owed_stops"), "owed_stops");
    if (!owed) return Problem{owed.error()};
    state.owed_stops = std::move(*owed);
  }
  return state;
}

}  // namespace sms::gateway
