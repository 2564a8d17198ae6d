#include "simulator/control_server.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <sstream>
#include <system_error>
#include <thread>
#include <vector>

#include "modbus_map/tables.h"
#include "simulator/bus_spec.h"

namespace sms::simulator {
namespace {

constexpr std::string_view kHelp =
    "commands: offline ID | online ID | drop P | corrupt P | corrupt-next [N] | garble ID on|off | late ID MS | "
    "error ID BITS | duplicate ID | timing on|off | get ID ADDR COUNT | set ID ADDR HEX... | field ID NAME | "
    "list | stats | help";
constexpr std::size_t kMaxLine = 4096;

std::vector<std::string> words_of(std::string_view line) {
  std::istringstream in{std::string(line)};
  std::vector<std::string> words;
  for (std::string word; in >> word;) words.push_back(word);
  return words;
}

std::string hex_bytes(const protocol::Bytes& bytes) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string text;
  for (const std::uint8_t byte : bytes) {
    if (!text.empty()) text += ' ';
    text += kDigits[byte >> 4];
    text += kDigits[byte & 0x0F];
  }
  return text;
}

std::optional<std::uint8_t> parse_hex_byte(std::string_view text) {
  if (text.size() > 2 && text[0] == '0' && (text[1] == 'x' || text[1] == 'X')) text.remove_prefix(2);
  if (text.empty() || text.size() > 2) return std::nullopt;
  const auto value = parse_number("0x" + std::string(text));
  if (!value) return std::nullopt;
  return static_cast<std::uint8_t>(*value);
}

}  // namespace

namespace {

// Argument readers with plain out-parameters (GCC 12 -O2 reports std::optional copies in
// ternaries as maybe-uninitialized).
bool read_id(const std::string& word, std::uint8_t& id) {
  const auto value = parse_number(word);
  if (!value || *value > 253) return false;
  id = static_cast<std::uint8_t>(*value);
  return true;
}

bool read_number(const std::string& word, std::uint32_t& number, std::uint32_t max = 0xFFFFFFFF) {
  const auto value = parse_number(word);
  if (!value || *value > max) return false;
  number = *value;
  return true;
}

bool has_servo(SimulatedBus& bus, std::uint8_t id) {
  for (const ServoSummary& servo : bus.servos()) {
    if (servo.config.id == id) return true;
  }
  return false;
}

std::string usage(std::string_view form) { return "error: usage: " + std::string(form); }
std::string unknown_id(std::uint8_t id) { return "error: no servo has ID " + std::to_string(id); }

std::string run_command(SimulatedBus& bus, const std::vector<std::string>& words) {
  const std::string& command = words[0];
  const std::size_t arguments = words.size() - 1;
  std::uint8_t id = 0;
  std::uint32_t number = 0;

  if (command == "help") return std::string(kHelp);
  if (command == "offline" || command == "online") {
    if (arguments != 1 || !read_id(words[1], id)) return usage(command + " ID");
    if (!has_servo(bus, id)) return unknown_id(id);
    bus.set_offline(id, command == "offline");
    return "ok";
  }
  if (command == "drop" || command == "corrupt") {
    const auto probability = arguments == 1 ? parse_probability(words[1]) : std::optional<double>();
    if (!probability) return usage(command + " P   (P from 0 to 1)");
    if (command == "drop") {
      bus.set_drop_probability(*probability);
    } else {
      bus.set_corrupt_probability(*probability);
    }
    return "ok";
  }
  if (command == "corrupt-next") {
    number = 1;
    if (arguments > 1 || (arguments == 1 && !read_number(words[1], number))) return usage("corrupt-next [N]");
    bus.corrupt_next_replies(number);
    return "ok";
  }
  if (command == "garble") {
    if (arguments != 2 || !read_id(words[1], id) || (words[2] != "on" && words[2] != "off")) {
      return usage("garble ID on|off");
    }
    if (!has_servo(bus, id)) return unknown_id(id);
    bus.set_garbled(id, words[2] == "on");
    return "ok";
  }
  if (command == "late") {
    if (arguments != 2 || !read_id(words[1], id) || !read_number(words[2], number)) return usage("late ID MS");
    if (!has_servo(bus, id)) return unknown_id(id);
    bus.set_reply_delay(id, std::chrono::milliseconds(number));
    return "ok";
  }
  if (command == "error") {
    if (arguments != 2 || !read_id(words[1], id) || !read_number(words[2], number, 0xFF)) {
      return usage("error ID BITS   (BITS 0-255, e.g. 0x04)");
    }
    if (!has_servo(bus, id)) return unknown_id(id);
    bus.set_error_bits(id, static_cast<std::uint8_t>(number));
    return "ok";
  }
  if (command == "duplicate") {
    if (arguments != 1 || !read_id(words[1], id)) return usage("duplicate ID");
    if (!has_servo(bus, id)) return unknown_id(id);
    bus.add_duplicate(id);
    return "ok";
  }
  if (command == "timing") {
    if (arguments != 1 || (words[1] != "on" && words[1] != "off")) return usage("timing on|off");
    bus.set_timing(words[1] == "on");
    return "ok";
  }
  if (command == "get") {
    std::uint32_t address = 0;
    std::uint32_t count = 1;
    if ((arguments != 2 && arguments != 3) || !read_id(words[1], id) || !read_number(words[2], address, 0xFFFF) ||
        (arguments == 3 && !read_number(words[3], count, 0xFFFF)) || count == 0) {
      return usage("get ID ADDR COUNT");
    }
    if (!has_servo(bus, id)) return unknown_id(id);
    const auto bytes = bus.read_memory(id, static_cast<std::uint16_t>(address), static_cast<std::uint16_t>(count));
    if (!bytes) {
      return "error: " + std::to_string(count) + " from address " + words[2] + " leave servo " + words[1] + "'s table";
    }
    return hex_bytes(*bytes);
  }
  if (command == "set") {
    std::uint32_t address = 0;
    if (arguments < 3 || !read_id(words[1], id) || !read_number(words[2], address, 0xFFFF)) {
      return usage("set ID ADDR HEX...   (e.g. set 3 42 00 08)");
    }
    protocol::Bytes bytes;
    for (std::size_t index = 3; index < words.size(); ++index) {
      const auto byte = parse_hex_byte(words[index]);
      if (!byte) return "error: '" + words[index] + "' is not a hex byte";
      bytes.push_back(*byte);
    }
    if (!has_servo(bus, id)) return unknown_id(id);
    if (!bus.write_memory(id, static_cast<std::uint16_t>(address), bytes)) {
      return "error: the write leaves servo " + words[1] + "'s table (SMSMB: whole registers, 2 bytes each)";
    }
    return "ok";
  }
  if (command == "field") {
    if (arguments != 2 || !read_id(words[1], id)) return usage("field ID NAME");
    if (!has_servo(bus, id)) return unknown_id(id);
    const auto value = bus.read_field(id, words[2]);
    if (!value) return "error: servo " + words[1] + "'s table has no field '" + words[2] + "'";
    return std::to_string(*value);
  }
  if (command == "list") {
    std::string text;
    for (const ServoSummary& servo : bus.servos()) {
      if (!text.empty()) text += ' ';
      text += std::to_string(servo.config.id) + ":" + std::string(modbus_map::table(servo.config.table).name) + ":" +
              std::string(protocol::to_string(servo.config.protocol)) + ":" + std::to_string(servo.config.baud);
      if (servo.offline) text += ":offline";
      if (servo.duplicate) text += ":duplicate";
    }
    return text;
  }
  if (command == "stats") {
    const BusStats stats = bus.stats();
    return "requests=" + std::to_string(stats.requests) + " replies=" + std::to_string(stats.replies) +
           " dropped=" + std::to_string(stats.dropped) + " corrupted=" + std::to_string(stats.corrupted) +
           " collisions=" + std::to_string(stats.collisions) + " checksum_errors=" + std::to_string(stats.checksum_errors) +
           " merged_requests=" + std::to_string(stats.merged_requests);
  }
  return "error: unknown command '" + command + "'; " + std::string(kHelp);
}

}  // namespace

std::string execute_control_command(SimulatedBus& bus, std::string_view line) {
  const auto words = words_of(line);
  if (words.empty()) return "error: empty command; " + std::string(kHelp);
  try {
    return run_command(bus, words);
  } catch (const std::exception& error) {
    return "error: " + std::string(error.what());
  }
}

class ControlServer::Impl {
 public:
  Impl(SimulatedBus& bus, std::string path) : bus_(bus), path_(std::move(path)) {
    sockaddr_un address{};
    address.sun_family = AF_UNIX;
    if (path_.size() >= sizeof address.sun_path) {
      throw std::system_error(ENAMETOOLONG, std::generic_category(), "control socket path " + path_);
    }
    std::memcpy(address.sun_path, path_.c_str(), path_.size() + 1);
    struct stat existing{};
    if (::lstat(path_.c_str(), &existing) == 0 && S_ISSOCK(existing.st_mode)) ::unlink(path_.c_str());
    listen_fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    if (listen_fd_ < 0) throw std::system_error(errno, std::generic_category(), "cannot create control socket");
    if (::bind(listen_fd_, reinterpret_cast<const sockaddr*>(&address), sizeof address) != 0 ||
        ::listen(listen_fd_, 8) != 0) {
      const int error = errno;
      ::close(listen_fd_);
      throw std::system_error(error, std::generic_category(), "cannot listen on control socket " + path_);
    }
    wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    thread_ = std::thread([this] { run(); });
  }

  ~Impl() {
    const std::uint64_t one = 1;
    [[maybe_unused]] const auto written = ::write(wake_fd_, &one, sizeof one);
    thread_.join();
    for (const Client& client : clients_) ::close(client.fd);
    ::close(listen_fd_);
    ::close(wake_fd_);
    ::unlink(path_.c_str());
  }

 private:
  struct Client {
    int fd;
    std::string pending;
  };

  void run() {
    for (;;) {
      std::vector<pollfd> fds{{wake_fd_, POLLIN, 0}, {listen_fd_, POLLIN, 0}};
      for (const Client& client : clients_) fds.push_back({client.fd, POLLIN, 0});
      if (::poll(fds.data(), fds.size(), -1) < 0 && errno != EINTR) return;
      if ((fds[0].revents & POLLIN) != 0) return;
      if ((fds[1].revents & POLLIN) != 0) {
        const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC);
        if (fd >= 0) clients_.push_back(Client{fd, {}});
      }
      for (std::size_t index = fds.size(); index-- > 2;) {
        if (fds[index].revents == 0) continue;
        if (!serve(clients_[index - 2])) {
          ::close(clients_[index - 2].fd);
          clients_.erase(clients_.begin() + static_cast<long>(index - 2));
        }
      }
    }
  }

  // Reads what arrived and answers every complete line; false when the client is gone.
  bool serve(Client& client) {
    char buffer[1024];
    const ssize_t received = ::read(client.fd, buffer, sizeof buffer);
    if (received <= 0) return false;
    client.pending.append(buffer, static_cast<std::size_t>(received));
    for (auto newline = client.pending.find('\n'); newline != std::string::npos;
         newline = client.pending.find('\n')) {
      std::string line = client.pending.substr(0, newline);
      client.pending.erase(0, newline + 1);
      if (!line.empty() && line.back() == '\r') line.pop_back();
      const std::string reply = execute_control_command(bus_, line) + "\n";
      if (::send(client.fd, reply.data(), reply.size(), MSG_NOSIGNAL) != static_cast<ssize_t>(reply.size())) {
        return false;
      }
    }
    return client.pending.size() <= kMaxLine;
  }

  SimulatedBus& bus_;
  std::string path_;
  int listen_fd_ = -1;
  int wake_fd_ = -1;
  std::vector<Client> clients_;
  std::thread thread_;
};

ControlServer::ControlServer(SimulatedBus& bus, std::string path)
    : impl_(std::make_unique<Impl>(bus, std::move(path))) {}
ControlServer::~ControlServer() = default;

}  // namespace sms::simulator
