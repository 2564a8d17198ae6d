#pragma once
// The real programs, as an integrator runs them: sms-sim processes on pseudo-terminals
// (faults injected through their --control socket) and an sms-gateway process with a
// configuration file, serving Modbus TCP on an ephemeral loopback port it reports in its log.
#include <stdlib.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/child_process.h"
#include "tests/support/modbus_client.h"

namespace sms::e2e {

using namespace std::chrono_literals;

inline std::string bin(const std::string& program) { return std::string(SMS_BIN_DIR) + "/" + program; }

class TempDir {
 public:
  TempDir() {
    std::string pattern = (std::filesystem::temp_directory_path() / "sms-e2e-XXXXXX").string();
    if (::mkdtemp(pattern.data()) == nullptr) throw std::runtime_error("mkdtemp failed");
    path_ = pattern;
  }
  ~TempDir() {
    std::error_code ignored;
    std::filesystem::remove_all(path_, ignored);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  std::string file(const std::string& name) const { return (path_ / name).string(); }

 private:
  std::filesystem::path path_;
};

template <typename F>
bool eventually(F condition, std::chrono::milliseconds timeout = 5s) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (condition()) return true;
    std::this_thread::sleep_for(5ms);
  }
  return condition();
}

// One sms-sim process: a whole simulated bus on a pty, with a control socket.
class SimProcess {
 public:
  // `args`: the bus description, e.g. {"--servo", "1:sts", "--servo", "4:sms1"}.
  SimProcess(const TempDir& dir, const std::string& name, std::vector<std::string> args, bool timing = false)
      : control_path_(dir.file(name + ".sock")) {
    std::vector<std::string> argv{bin("sms-sim")};
    argv.insert(argv.end(), args.begin(), args.end());
    argv.insert(argv.end(), {"--control", control_path_, "--seed", "7"});
    if (!timing) argv.push_back("--no-timing");
    process_ = std::make_unique<ChildProcess>(argv);
    const auto line = process_->wait_for_line("/dev/", 10s);
    if (!line) throw std::runtime_error("sms-sim printed no pty path:\n" + process_->output());
    pty_ = line->substr(line->find("/dev/"));
  }

  const std::string& pty() const { return pty_; }

  // One control command ("offline 2", "field 1 goal_position" ...); its reply line.
  std::string control(const std::string& command) {
    const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_un address{};
    address.sun_family = AF_UNIX;
    control_path_.copy(address.sun_path, sizeof address.sun_path - 1);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
      ::close(fd);
      throw std::runtime_error("cannot connect to the simulator's control socket " + control_path_);
    }
    const std::string line = command + "\n";
    if (::write(fd, line.data(), line.size()) != static_cast<ssize_t>(line.size())) {
      ::close(fd);
      throw std::runtime_error("control write failed");
    }
    std::string reply;
    char c;
    while (::read(fd, &c, 1) == 1 && c != '\n') reply += c;
    ::close(fd);
    return reply;
  }

  // A field of a servo as the simulator holds it (signed where the field is).
  long field(int id, const std::string& name) {
    const std::string reply = control("field " + std::to_string(id) + " " + name);
    try {
      return std::stol(reply);
    } catch (const std::exception&) {
      throw std::runtime_error("field " + std::to_string(id) + " " + name + ": " + reply);
    }
  }

  ChildProcess& process() { return *process_; }

 private:
  std::string control_path_;
  std::unique_ptr<ChildProcess> process_;
  std::string pty_;
};

// One sms-gateway process on a configuration file (written by the test) or on --simulate.
class GatewayProcess {
 public:
  // `extra_args` go after the generated --listen 127.0.0.1:0. `buses` = how many discovery
  // summaries to wait for.
  GatewayProcess(std::vector<std::string> args, int buses) {
    std::vector<std::string> argv{bin("sms-gateway")};
    argv.insert(argv.end(), args.begin(), args.end());
    argv.insert(argv.end(), {"--listen", "127.0.0.1:0"});
    process_ = std::make_unique<ChildProcess>(argv);
    const std::string marker = "listening on 127.0.0.1:";
    const auto line = process_->wait_for_line(marker, 15s);
    if (!line) throw std::runtime_error("sms-gateway did not start listening:\n" + process_->output());
    port_ = static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
    for (int i = 0; i < buses; ++i) {
      if (!process_->wait_for_line("servos online", 15s)) {
        throw std::runtime_error("sms-gateway did not report its buses:\n" + process_->output());
      }
    }
  }

  static GatewayProcess with_config(const TempDir& dir, const std::string& yaml, int buses) {
    const std::string path = dir.file("gateway.yaml");
    std::ofstream(path) << yaml;
    return GatewayProcess({"--config", path}, buses);
  }

  std::uint16_t port() const { return port_; }
  ChildProcess& process() { return *process_; }

 private:
  std::unique_ptr<ChildProcess> process_;
  std::uint16_t port_ = 0;
};

// Replaces every `what` in `text`.
inline std::string substitute(std::string text, const std::string& what, const std::string& with) {
  for (std::size_t at = 0; (at = text.find(what, at)) != std::string::npos; at += with.size()) {
    text.replace(at, what.size(), with);
  }
  return text;
}

// Waits until `unit` has been polled at least once (its cache-age register is not "never").
inline void wait_until_polled(std::uint16_t port, int unit) {
  ModbusClient client(port, unit);
  if (!eventually([&] {
        const auto age = client.read_input(1002, 1);
        return age.ok() && age.values[0] != 0xFFFF;
      })) {
    throw std::runtime_error("unit " + std::to_string(unit) + " was never polled");
  }
}

}  // namespace sms::e2e
