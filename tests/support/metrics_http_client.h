#pragma once
// A plain-socket HTTP/1.1 client for the metrics endpoint tests, and a parser for the
// Prometheus text the endpoint serves. Written without Beast so the server is checked against
// an independent reading of the protocol.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <map>
#include <optional>
#include <regex>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include "tests/support/loopback_client.h"

namespace sms::test {

struct HttpResponse {
  int status = 0;
  std::map<std::string, std::string> headers;  // names in lower case
  std::string body;

  std::string header(const std::string& name) const {
    const auto found = headers.find(name);
    return found == headers.end() ? std::string() : found->second;
  }
};

class HttpConnection {
 public:
  explicit HttpConnection(std::uint16_t port) : fd_(connect_loopback(port)) {}
  ~HttpConnection() {
    if (fd_ >= 0) ::close(fd_);
  }
  HttpConnection(const HttpConnection&) = delete;
  HttpConnection& operator=(const HttpConnection&) = delete;

  void send(const std::string& text) {
    std::size_t sent = 0;
    while (sent < text.size()) {
      const ssize_t n = ::send(fd_, text.data() + sent, text.size() - sent, MSG_NOSIGNAL);
      if (n <= 0) throw std::runtime_error("send: " + std::string(std::strerror(errno)));
      sent += static_cast<std::size_t>(n);
    }
  }

  // One response: headers, then Content-Length bytes of body (none for a HEAD request).
  // nullopt when the connection closed or nothing complete came within the timeout.
  std::optional<HttpResponse> read_response(bool head = false,
                                            std::chrono::milliseconds timeout = std::chrono::seconds{5}) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    std::size_t header_end = std::string::npos;
    while ((header_end = pending_.find("\r\n\r\n")) == std::string::npos) {
      if (!receive_more(deadline)) return std::nullopt;
    }
    HttpResponse response;
    const std::string head_text = pending_.substr(0, header_end);
    pending_.erase(0, header_end + 4);
    std::size_t line_end = head_text.find("\r\n");
    const std::string status_line = head_text.substr(0, line_end);
    static const std::regex kStatus(R"(HTTP/1\.[01] (\d{3}) .*)");
    std::smatch match;
    if (!std::regex_match(status_line, match, kStatus)) throw std::runtime_error("bad status line: " + status_line);
    response.status = std::stoi(match[1]);
    while (line_end != std::string::npos) {
      const std::size_t start = line_end + 2;
      line_end = head_text.find("\r\n", start);
      const std::string line =
          head_text.substr(start, line_end == std::string::npos ? std::string::npos : line_end - start);
      const auto colon = line.find(':');
      if (colon == std::string::npos) throw std::runtime_error("bad header line: " + line);
      std::string name = line.substr(0, colon);
      std::transform(name.begin(), name.end(), name.begin(), [](unsigned char c) { return std::tolower(c); });
      std::string value = line.substr(colon + 1);
      value.erase(0, value.find_first_not_of(' '));
      response.headers[name] = value;
    }
    const std::size_t length =
        head ? 0
             : std::stoul(response.header("content-length").empty() ? std::string("0")
                                                                    : response.header("content-length"));
    while (pending_.size() < length) {
      if (!receive_more(deadline)) return std::nullopt;
    }
    response.body = pending_.substr(0, length);
    pending_.erase(0, length);
    return response;
  }

  // True when the server closed the connection within the timeout (and sent nothing more).
  bool closed_by_peer(std::chrono::milliseconds timeout = std::chrono::seconds{5}) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    const std::size_t before = pending_.size();
    while (receive_more(deadline)) {
    }
    return closed_ && pending_.size() == before;
  }

  // Bytes received but not yet taken by read_response().
  const std::string& pending() const { return pending_; }

 private:
  bool receive_more(std::chrono::steady_clock::time_point deadline) {
    if (closed_) return false;
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now()).count();
    if (left <= 0) return false;
    pollfd pfd{fd_, POLLIN, 0};
    if (::poll(&pfd, 1, static_cast<int>(left)) <= 0) return false;
    char buffer[4096];
    const ssize_t n = ::recv(fd_, buffer, sizeof buffer, 0);
    if (n <= 0) {
      closed_ = true;
      return false;
    }
    pending_.append(buffer, static_cast<std::size_t>(n));
    return true;
  }

  int fd_ = -1;
  std::string pending_;
  bool closed_ = false;
};

// One request on a fresh connection that the client asks to close.
inline HttpResponse http_request(std::uint16_t port, const std::string& method, const std::string& target) {
  HttpConnection connection(port);
  connection.send(method + " " + target + " HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n");
  auto response = connection.read_response(method == "HEAD");
  if (!response) throw std::runtime_error(method + " " + target + ": no complete response");
  return *response;
}

// The samples of a Prometheus text exposition (format 0.0.4), checked line by line as it is
// read: HELP then TYPE before each family's samples, each family once and contiguous, counter
// names ending in _total, valid names and label syntax, numeric values, one trailing newline.
struct Exposition {
  std::map<std::string, std::string> samples;  // `name{labels}` as written -> value text
  std::map<std::string, std::string> types;    // family -> counter | gauge
  std::map<std::string, std::string> help;     // family -> help text as written
  std::vector<std::string> families;           // in order of appearance
  std::vector<std::string> errors;             // format violations, empty when valid

  bool has(const std::string& key) const { return samples.count(key) > 0; }
  std::string value(const std::string& key) const {
    const auto found = samples.find(key);
    return found == samples.end() ? std::string("(absent)") : found->second;
  }
  // Samples of one family.
  std::size_t count(const std::string& family) const {
    std::size_t n = 0;
    for (const auto& [key, value] : samples) {
      if (key == family || key.rfind(family + "{", 0) == 0) ++n;
    }
    return n;
  }
};

inline Exposition parse_exposition(const std::string& text) {
  static const std::regex kHelp(R"(# HELP ([a-zA-Z_:][a-zA-Z0-9_:]*) (.*))");
  static const std::regex kType(R"(# TYPE ([a-zA-Z_:][a-zA-Z0-9_:]*) (counter|gauge))");
  static const std::regex kSample(
      R"(([a-zA-Z_:][a-zA-Z0-9_:]*)(\{([a-zA-Z_][a-zA-Z0-9_]*="([^"\\\n]|\\[\\"n])*")(,[a-zA-Z_][a-zA-Z0-9_]*="([^"\\\n]|\\[\\"n])*")*\})? ([^ ]+))");
  Exposition out;
  if (text.empty() || text.back() != '\n') out.errors.push_back("text does not end with a newline");
  std::set<std::string> seen;
  std::string family;
  std::string expecting_type;
  std::size_t start = 0;
  while (start < text.size()) {
    const std::size_t end = text.find('\n', start);
    const std::string line = text.substr(start, end == std::string::npos ? std::string::npos : end - start);
    start = end == std::string::npos ? text.size() : end + 1;
    std::smatch match;
    if (!expecting_type.empty()) {
      if (!std::regex_match(line, match, kType) || match[1] != expecting_type) {
        out.errors.push_back("HELP of " + expecting_type + " not followed by its TYPE: " + line);
      } else {
        out.types[expecting_type] = match[2];
        if (match[2] == "counter" && !expecting_type.ends_with("_total")) {
          out.errors.push_back("counter without _total: " + expecting_type);
        }
      }
      family = expecting_type;
      expecting_type.clear();
      continue;
    }
    if (std::regex_match(line, match, kHelp)) {
      if (!seen.insert(match[1]).second) out.errors.push_back("family twice: " + match[1].str());
      expecting_type = match[1];
      out.help[match[1]] = match[2];
      out.families.push_back(match[1]);
      continue;
    }
    if (std::regex_match(line, match, kSample)) {
      if (match[1] != family) out.errors.push_back("sample outside its family (" + family + "): " + line);
      const std::string value = match[7];
      try {
        std::size_t used = 0;
        (void)std::stod(value, &used);
        if (used != value.size()) out.errors.push_back("value is not a number: " + line);
      } catch (const std::exception&) {
        out.errors.push_back("value is not a number: " + line);
      }
      const std::string key = line.substr(0, line.rfind(' '));
      if (!out.samples.emplace(key, value).second) out.errors.push_back("sample twice: " + key);
      continue;
    }
    out.errors.push_back("not a HELP, TYPE or sample line: " + line);
  }
  return out;
}

}  // namespace sms::test
