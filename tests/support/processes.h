#pragma once
// The real programs, as an integrator runs them: sms-sim processes on pseudo-terminals
// (faults injected through their --control socket) and an sms-gateway process with a
// configuration file, serving Modbus TCP on an ephemeral loopback port it reports in its log.
// Used by the end-to-end tests (tests/e2e) and the benchmarks (bench/); no GoogleTest here.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/await.h"
#include "tests/support/child_process.h"
#include "tests/support/modbus_client.h"

namespace sms::test {

using namespace std::chrono_literals;

inline std::string bin(const std::string& program) { return std::string(SMS_BIN_DIR) + "/" + program; }

class TempDir {
 public:
  TempDir() {
    std::string pattern = (std::filesystem::temp_directory_path() / "sms-test-XXXXXX").string();
    if (::mkdtemp(pattern.data()) == nullptr) throw std::runtime_error("mkdtemp failed");
    path_ = pattern;
  }
  ~TempDir() {
    std::error_code ignored;
    std::filesystem::remove_all(path_, ignored);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  std::string path() const { return path_.string(); }
  std::string file(const std::string& name) const { return (path_ / name).string(); }

 private:
  std::filesystem::path path_;
};

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

// One sms-gateway process on a configuration file (written by the caller) or on --simulate,
// started with --listen 127.0.0.1:0: its port is the one its log reports. Ready when it listens
// and has reported each bus's discovery. Destroyed while running, it is killed (SIGKILL); stop()
// is the graceful way (SIGTERM, as systemd stops it).
class GatewayProcess {
 public:
  // `args` go before the generated --listen 127.0.0.1:0 (which overrides the configuration's).
  // `buses` = how many discovery summaries ("... servos online") to wait for. `program`: the
  // sms-gateway to run (the benchmarks may measure another build).
  GatewayProcess(std::vector<std::string> args, int buses, const std::string& program = bin("sms-gateway")) {
    std::vector<std::string> argv{program};
    argv.insert(argv.end(), args.begin(), args.end());
    argv.insert(argv.end(), {"--listen", "127.0.0.1:0"});
    process_ = std::make_unique<ChildProcess>(argv);
    const std::string marker = "listening on 127.0.0.1:";
    const auto line = process_->wait_for_line(marker, kStartTimeout);
    if (!line) throw std::runtime_error("sms-gateway did not start listening:\n" + process_->output());
    port_ = static_cast<std::uint16_t>(std::stoi(line->substr(line->find(marker) + marker.size())));
    for (int i = 0; i < buses; ++i) {
      if (!process_->wait_for_line("servos online", kStartTimeout)) {
        throw std::runtime_error("sms-gateway did not report its buses:\n" + process_->output());
      }
    }
  }

  // The configuration `yaml` written to `dir`/gateway.yaml.
  static GatewayProcess with_config(const TempDir& dir, const std::string& yaml, int buses,
                                    std::vector<std::string> extra_args = {},
                                    const std::string& program = bin("sms-gateway")) {
    const std::string path = dir.file("gateway.yaml");
    std::ofstream(path) << yaml;
    std::vector<std::string> args{"--config", path};
    args.insert(args.end(), extra_args.begin(), extra_args.end());
    return GatewayProcess(args, buses, program);
  }

  std::uint16_t port() const { return port_; }
  pid_t pid() const { return process_->pid(); }
  ChildProcess& process() { return *process_; }

  // SIGTERM, then the exit status (0 for a clean stop); SIGKILL when it has not stopped after
  // kStopTimeout.
  int stop() {
    if (const auto status = process_->wait_exit(std::chrono::milliseconds{0})) return *status;
    process_->signal(SIGTERM);
    if (const auto status = process_->wait_exit(kStopTimeout)) return *status;
    process_->signal(SIGKILL);
    return process_->wait_exit(kStopTimeout).value_or(-1);
  }

 private:
  // Start-up opens every bus and discovers its servos: longer than one awaited condition.
  static constexpr std::chrono::seconds kStartTimeout{15};
  static constexpr std::chrono::seconds kStopTimeout{10};

  std::unique_ptr<ChildProcess> process_;
  std::uint16_t port_ = 0;
};

// A free TCP port on 127.0.0.1 (bound and released; the child binds it right after).
inline std::uint16_t free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof address;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) != 0) {
    const int error = errno;
    ::close(fd);
    throw std::runtime_error(std::string("cannot find a free port on 127.0.0.1: ") + std::strerror(error));
  }
  ::close(fd);
  return ntohs(address.sin_port);
}

// One mosquitto process (Debian's /usr/sbin/mosquitto) on a free loopback port; `extra` lines go into its listener's
// configuration (TLS, passwords).
class MosquittoBroker {
 public:
  MosquittoBroker(const TempDir& dir, std::string extra = "allow_anonymous true\n")
      : config_(dir.file("mosquitto-" + std::to_string(++count_) + ".conf")),
        port_(free_port()),
        extra_(std::move(extra)) {
    start();
  }
  void start() {
    std::ofstream(config_) << "listener " << port_ << " 127.0.0.1\n" << extra_ << "persistence false\n";
    process_ = std::make_unique<ChildProcess>(std::vector<std::string>{"/usr/sbin/mosquitto", "-c", config_, "-v"});
    if (!process_->wait_for_line("running", 10s))
      throw std::runtime_error("mosquitto did not start:\n" + process_->output());
  }
  void kill() {
    process_->signal(SIGKILL);
    process_->wait_exit(5s);
  }
  std::uint16_t port() const { return port_; }
  ChildProcess& process() { return *process_; }

 private:
  static inline int count_ = 0;
  std::string config_;
  std::uint16_t port_;
  std::string extra_;
  std::unique_ptr<ChildProcess> process_;
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
  await_or_throw(
      [&] {
        const auto age = client.read_input(1002, 1);
        return age.ok() && age.values[0] != 0xFFFF;
      },
      "unit " + std::to_string(unit) + " polled once (its cache age, input register 1002, not 0xFFFF)");
}

}  // namespace sms::test
