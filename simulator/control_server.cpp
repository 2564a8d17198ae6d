#include "simulator/control_server.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <optional>
#include <sstream>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

#include "modbus_map/tables.h"
#include "simulator/bus_spec.h"

namespace sms::simulator {
namespace {

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

// A steady-clock time as microseconds (CLOCK_MONOTONIC: the same clock in every process of the
// machine), "-" for none.
std::string monotonic_us(const std::optional<std::chrono::steady_clock::time_point>& when) {
  if (!when) return "-";
  return std::to_string(std::chrono::duration_cast<std::chrono::microseconds>(when->time_since_epoch()).count());
}

std::string usage(std::string_view form) { return "error: usage: " + std::string(form); }
std::string unknown_id(std::uint8_t id) { return "error: no servo has ID " + std::to_string(id); }

using Words = std::vector<std::string>;

// nullopt: the words do not fit the command's form (answered with its usage).
using Handler = std::optional<std::string> (*)(SimulatedBus&, const Words&);

struct ControlCommand {
  std::string_view name;
  std::string_view form;  // "garble ID on|off": the help line and the usage error
  std::string_view hint;  // more for the usage error: "   (P from 0 to 1)"
  Handler run;
};

std::string help_text();

// A command on one servo: `words[1]` is its ID; `act` runs once the ID is read and the servo exists.
template <typename Act>
std::optional<std::string> on_servo(SimulatedBus& bus, const Words& words, std::size_t arguments, Act act) {
  std::uint8_t id = 0;
  if (words.size() - 1 != arguments || !read_id(words[1], id)) return std::nullopt;
  if (!has_servo(bus, id)) return unknown_id(id);
  return act(id);
}

std::optional<std::string> set_probability(const Words& words, const std::function<void(double)>& set) {
  const auto probability = words.size() == 2 ? parse_probability(words[1]) : std::optional<double>();
  if (!probability) return std::nullopt;
  set(*probability);
  return "ok";
}

// The control commands, one row each (the help text is made from this table).
const std::array<ControlCommand, 18> kCommands{{
    {"offline", "offline ID", "",
     [](SimulatedBus& bus, const Words& w) {
       return on_servo(bus, w, 1, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.set_offline(id, true);
         return "ok";
       });
     }},
    {"online", "online ID", "",
     [](SimulatedBus& bus, const Words& w) {
       return on_servo(bus, w, 1, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.set_offline(id, false);
         return "ok";
       });
     }},
    {"drop", "drop P", "   (P from 0 to 1)",
     [](SimulatedBus& bus, const Words& w) {
       return set_probability(w, [&](double p) { bus.set_drop_probability(p); });
     }},
    {"corrupt", "corrupt P", "   (P from 0 to 1)",
     [](SimulatedBus& bus, const Words& w) {
       return set_probability(w, [&](double p) { bus.set_corrupt_probability(p); });
     }},
    {"corrupt-next", "corrupt-next [N]", "",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       std::uint32_t number = 1;
       if (w.size() > 2 || (w.size() == 2 && !read_number(w[1], number))) return std::nullopt;
       bus.corrupt_next_replies(number);
       return "ok";
     }},
    {"garble", "garble ID on|off", "",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       if (w.size() != 3 || (w[2] != "on" && w[2] != "off")) return std::nullopt;
       return on_servo(bus, w, 2, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.set_garbled(id, w[2] == "on");
         return "ok";
       });
     }},
    {"late", "late ID MS", "",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       std::uint32_t ms = 0;
       if (w.size() != 3 || !read_number(w[2], ms)) return std::nullopt;
       return on_servo(bus, w, 2, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.set_reply_delay(id, std::chrono::milliseconds(ms));
         return "ok";
       });
     }},
    {"error", "error ID BITS", "   (BITS 0-255, e.g. 0x04)",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       std::uint32_t bits = 0;
       if (w.size() != 3 || !read_number(w[2], bits, 0xFF)) return std::nullopt;
       return on_servo(bus, w, 2, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.set_error_bits(id, static_cast<std::uint8_t>(bits));
         return "ok";
       });
     }},
    {"duplicate", "duplicate ID", "",
     [](SimulatedBus& bus, const Words& w) {
       return on_servo(bus, w, 1, [&](std::uint8_t id) -> std::optional<std::string> {
         bus.add_duplicate(id);
         return "ok";
       });
     }},
    {"timing", "timing on|off", "",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       if (w.size() != 2 || (w[1] != "on" && w[1] != "off")) return std::nullopt;
       bus.set_timing(w[1] == "on");
       return "ok";
     }},
    {"get", "get ID ADDR COUNT", "",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       std::uint32_t address = 0;
       std::uint32_t count = 1;
       if ((w.size() != 3 && w.size() != 4) || !read_number(w[2], address, 0xFFFF) ||
           (w.size() == 4 && !read_number(w[3], count, 0xFFFF)) || count == 0) {
         return std::nullopt;
       }
       return on_servo(bus, w, w.size() - 1, [&](std::uint8_t id) -> std::optional<std::string> {
         const auto bytes = bus.read_memory(id, static_cast<std::uint16_t>(address), static_cast<std::uint16_t>(count));
         if (!bytes)
           return "error: " + std::to_string(count) + " from address " + w[2] + " leave servo " + w[1] + "'s table";
         return hex_bytes(*bytes);
       });
     }},
    {"set", "set ID ADDR HEX...", "   (e.g. set 3 42 00 08)",
     [](SimulatedBus& bus, const Words& w) -> std::optional<std::string> {
       std::uint32_t address = 0;
       if (w.size() < 4 || !read_number(w[2], address, 0xFFFF)) return std::nullopt;
       protocol::Bytes bytes;
       for (std::size_t index = 3; index < w.size(); ++index) {
         const auto byte = parse_hex_byte(w[index]);
         if (!byte) return "error: '" + w[index] + "' is not a hex byte";
         bytes.push_back(*byte);
       }
       return on_servo(bus, w, w.size() - 1, [&](std::uint8_t id) -> std::optional<std::string> {
         if (!bus.write_memory(id, static_cast<std::uint16_t>(address), bytes)) {
           return "error: the write leaves servo " + w[1] + "'s table (SMSMB: whole registers, 2 bytes each)";
         }
         return "ok";
       });
     }},
    {"field", "field ID NAME", "",
     [](SimulatedBus& bus, const Words& w) {
       return on_servo(bus, w, 2, [&](std::uint8_t id) -> std::optional<std::string> {
         const auto value = bus.read_field(id, w[2]);
         if (!value) return "error: servo " + w[1] + "'s table has no field '" + w[2] + "'";
         return std::to_string(*value);
       });
     }},
    {"motion", "motion ID", "",
     [](SimulatedBus& bus, const Words& w) {
       return on_servo(bus, w, 1, [&](std::uint8_t id) -> std::optional<std::string> {
         for (const ServoSummary& servo : bus.servos()) {
           if (servo.config.id != id || servo.duplicate) continue;
           return "started_us=" + monotonic_us(servo.move_started) + " arrived_us=" + monotonic_us(servo.arrived) +
                  " position=" + std::to_string(servo.present_position) +
                  " goal=" + std::to_string(servo.goal_position) +
                  " at_goal_write=" + std::to_string(std::lround(servo.position_at_goal)) +
                  " read_before_goal=" + std::to_string(std::lround(servo.read_before_goal)) +
                  " reversed=" + (servo.reversed ? "1" : "0") +
                  " turned_back=" + std::to_string(std::lround(servo.turned_back)) +
                  " heartbeat_stops=" + std::to_string(servo.heartbeat_stops);
         }
         return unknown_id(id);
       });
     }},
    {"list", "list", "",
     [](SimulatedBus& bus, const Words&) -> std::optional<std::string> {
       std::string text;
       for (const ServoSummary& servo : bus.servos()) {
         if (!text.empty()) text += ' ';
         text += std::to_string(servo.config.id) + ":" + std::string(modbus_map::table(servo.config.table).name) + ":" +
                 std::string(protocol::to_string(servo.config.protocol)) + ":" + std::to_string(servo.config.baud);
         if (servo.offline) text += ":offline";
         if (servo.duplicate) text += ":duplicate";
       }
       return text;
     }},
    {"stats", "stats", "",
     [](SimulatedBus& bus, const Words&) -> std::optional<std::string> {
       const BusStats stats = bus.stats();
       return "requests=" + std::to_string(stats.requests) + " replies=" + std::to_string(stats.replies) +
              " dropped=" + std::to_string(stats.dropped) + " corrupted=" + std::to_string(stats.corrupted) +
              " collisions=" + std::to_string(stats.collisions) +
              " checksum_errors=" + std::to_string(stats.checksum_errors) +
              " merged_requests=" + std::to_string(stats.merged_requests);
     }},
    {"holds", "holds", "",
     [](SimulatedBus& bus, const Words&) -> std::optional<std::string> {
       std::string text;
       for (const Hold& hold : bus.holds()) {
         if (!text.empty()) text += ' ';
         text += monotonic_us(hold.ended) + ":" +
                 std::to_string(std::chrono::duration_cast<std::chrono::microseconds>(hold.held).count());
       }
       return text.empty() ? "none" : text;
     }},
    {"help", "help", "", [](SimulatedBus&, const Words&) -> std::optional<std::string> { return help_text(); }},
}};

std::string help_text() {
  std::string text = "commands:";
  for (const ControlCommand& command : kCommands) {
    text += (text.size() > 9 ? " | " : " ") + std::string(command.form);
  }
  return text;
}

std::string run_command(SimulatedBus& bus, const Words& words) {
  for (const ControlCommand& command : kCommands) {
    if (command.name != words[0]) continue;
    if (auto answer = command.run(bus, words)) return *answer;
    return usage(std::string(command.form) + std::string(command.hint));
  }
  return "error: unknown command '" + words[0] + "'; " + help_text();
}

}  // namespace

std::string execute_control_command(SimulatedBus& bus, std::string_view line) {
  const auto words = words_of(line);
  if (words.empty()) return "error: empty command; " + help_text();
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
    struct stat existing {};
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
    for (auto newline = client.pending.find('\n'); newline != std::string::npos; newline = client.pending.find('\n')) {
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
