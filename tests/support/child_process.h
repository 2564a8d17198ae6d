#pragma once
// A program under test run as a real child process: stdout and stderr are collected by a
// reader thread (so the child never blocks on a full pipe) and can be waited on line by line.
// The destructor sends SIGKILL if the child still runs, so a failing test leaves nothing behind.
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/await.h"

extern char** environ;

namespace sms::test {

class ChildProcess {
 public:
  // `extra_environment`: "NAME=value" entries added to (or replacing) this process's environment.
  explicit ChildProcess(std::vector<std::string> argv, std::vector<std::string> extra_environment = {})
      : argv_(std::move(argv)) {
    int out_pipe[2];
    if (::pipe2(out_pipe, O_CLOEXEC) != 0) throw std::runtime_error("pipe: " + std::string(std::strerror(errno)));
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    // stdout and stderr both land in the one pipe, in the order the child writes them.
    posix_spawn_file_actions_adddup2(&actions, out_pipe[1], STDOUT_FILENO);
    posix_spawn_file_actions_adddup2(&actions, out_pipe[1], STDERR_FILENO);
    std::vector<char*> args;
    for (auto& arg : argv_) args.push_back(arg.data());
    args.push_back(nullptr);
    std::vector<std::string> environment = std::move(extra_environment);
    for (char** entry = environ; *entry != nullptr; ++entry) {
      const std::string text = *entry;
      const std::string name = text.substr(0, text.find('=') + 1);
      const bool replaced = std::any_of(environment.begin(), environment.end(),
                                        [&](const std::string& extra) { return extra.rfind(name, 0) == 0; });
      if (!replaced) environment.push_back(text);
    }
    std::vector<char*> env;
    for (auto& entry : environment) env.push_back(entry.data());
    env.push_back(nullptr);
    const int error = ::posix_spawn(&pid_, args[0], &actions, nullptr, args.data(), env.data());
    posix_spawn_file_actions_destroy(&actions);
    ::close(out_pipe[1]);
    if (error != 0) {
      ::close(out_pipe[0]);
      throw std::runtime_error("cannot start " + argv_[0] + ": " + std::strerror(error));
    }
    reader_ = std::thread([this, fd = out_pipe[0]] { read_output(fd); });
  }

  ~ChildProcess() {
    if (!exit_status_) {
      ::kill(pid_, SIGKILL);
      wait_exit(std::chrono::seconds{10});
    }
    if (reader_.joinable()) reader_.join();
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  pid_t pid() const { return pid_; }

  void signal(int number) { ::kill(pid_, number); }

  // Exit code (or 128 + signal), or nullopt when the child still runs after `timeout`.
  std::optional<int> wait_exit(std::chrono::milliseconds timeout) {
    if (exit_status_) return exit_status_;
    int status = 0;
    if (!poll_until([&] { return ::waitpid(pid_, &status, WNOHANG) == pid_; }, timeout)) return std::nullopt;
    exit_status_ = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    // Everything the child wrote is in the pipe: let the reader take it all before anyone
    // looks at output().
    std::unique_lock lock(mutex_);
    changed_.wait_for(lock, kAwaitTimeout, [this] { return output_closed_; });
    return exit_status_;
  }

  // The first output line containing `text` (searching everything written so far), or
  // nullopt when none came within `timeout` or the child closed its output first.
  std::optional<std::string> wait_for_line(const std::string& text, std::chrono::milliseconds timeout) {
    std::unique_lock lock(mutex_);
    std::size_t searched = 0;
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    for (;;) {
      for (; searched < lines_.size(); ++searched) {
        if (lines_[searched].find(text) != std::string::npos) return lines_[searched];
      }
      if (output_closed_) return std::nullopt;
      if (changed_.wait_until(lock, deadline) == std::cv_status::timeout && searched == lines_.size()) {
        return std::nullopt;
      }
    }
  }

  // Every line so far, for failure messages.
  std::string output() {
    std::lock_guard lock(mutex_);
    std::string all;
    for (const auto& line : lines_) all += line + "\n";
    return all + partial_;
  }

 private:
  void read_output(int fd) {
    char buffer[4096];
    for (;;) {
      const ssize_t n = ::read(fd, buffer, sizeof buffer);
      if (n <= 0) break;
      std::lock_guard lock(mutex_);
      partial_.append(buffer, static_cast<std::size_t>(n));
      for (std::size_t end; (end = partial_.find('\n')) != std::string::npos;) {
        lines_.push_back(partial_.substr(0, end));
        partial_.erase(0, end + 1);
      }
      changed_.notify_all();
    }
    ::close(fd);
    std::lock_guard lock(mutex_);
    output_closed_ = true;
    changed_.notify_all();
  }

  std::vector<std::string> argv_;
  pid_t pid_ = -1;
  std::optional<int> exit_status_;
  std::thread reader_;
  std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<std::string> lines_;
  std::string partial_;
  bool output_closed_ = false;
};

// A program run to its end: its exit status (-1 when it ran past `timeout`) and all it wrote.
struct Finished {
  int status = -1;
  std::string output;  // stdout and stderr together
};
inline Finished run_to_end(const std::vector<std::string>& argv, std::chrono::milliseconds timeout) {
  ChildProcess process(argv);
  const auto status = process.wait_exit(timeout);  // and has read everything the child wrote
  return Finished{status.value_or(-1), process.output()};
}

}  // namespace sms::test
