#pragma once
// The console's request parsing, pure (no sockets): paths against route patterns, query and
// cookie values, and the JSON bodies and WebSocket messages the pages send. Every function
// takes untrusted text and says what is wrong with it instead of throwing; tests/fuzz's
// console_request_fuzz drives them with arbitrary bytes.
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "protocol/expected.h"

namespace sms::gateway::console {

// Named parts of a matched path: "/servo/{unit}" against "/servo/3" gives {"unit", "3"}.
class PathParams {
 public:
  void add(std::string_view name, std::string value) { values_.emplace_back(std::string(name), std::move(value)); }
  std::optional<std::string_view> get(std::string_view name) const;

 private:
  std::vector<std::pair<std::string, std::string>> values_;
};

// The path of a request target (before '?').
std::string_view path_of(std::string_view target);
// Whether `path` matches `pattern` ({name} stands for one non-empty segment, percent-decoded);
// fills `params`.
bool match_path(std::string_view pattern, std::string_view path, PathParams& params);
// %XX and '+' decoded; nullopt for a broken escape or a decoded NUL.
std::optional<std::string> percent_decode(std::string_view text, bool plus_is_space = false);
// `text` as a query value: every byte but the unreserved (A-Z a-z 0-9 - . _ ~) and `/` as %XX.
std::string percent_encode(std::string_view text);
// The value of query parameter `name` in `target`, decoded.
std::optional<std::string> query_value(std::string_view target, std::string_view name);
// The value of cookie `name` in a Cookie header.
std::optional<std::string> cookie_value(std::string_view header, std::string_view name);
// A Modbus unit id as written in a URL: 1-255, decimal digits only.
std::optional<std::uint8_t> parse_unit(std::string_view text);

// --- bodies (JSON objects) --------------------------------------------------------------------

struct LoginRequest {
  std::string user;
  std::string password;
};
Expected<LoginRequest> parse_login(std::string_view body);

// A field of the servo's control table := value (the value as a Modbus client sees it).
struct FieldWrite {
  std::string field;
  std::int64_t value = 0;
};
Expected<FieldWrite> parse_field_write(std::string_view body);

// The e-stop button: latch (true) or reset (false; the page asks for a confirmation first).
struct EstopRequest {
  bool latch = true;
};
Expected<EstopRequest> parse_estop(std::string_view body);

// --- WebSocket messages of the servo page (the jog panel) ---------------------------------------

// {"type":"heartbeat"} while a hold-to-run button is held (and otherwise, to keep the page live);
// {"type":"jog","mode":"position","value":N} / {"type":"jog","mode":"speed","value":N}: start
//   (or change) a hold-to-run move, which lasts while heartbeats come;
// {"type":"release"}: the button was let go;
// {"type":"torque","on":true|false}.
struct JogMessage {
  enum class Kind : std::uint8_t { Heartbeat, JogPosition, JogSpeed, Release, Torque };
  Kind kind = Kind::Heartbeat;
  std::int64_t value = 0;
  bool on = false;
};
Expected<JogMessage> parse_jog_message(std::string_view text);

// Untrusted text for an error message or a log line: at most `max` bytes (then "..."), printable
// ASCII kept, control characters and other bytes as '?'. Not HTML-escaped: JSON encoding or
// html_escape() is the caller's.
std::string printable(std::string_view text, std::size_t max = 80);
// `text` with & < > " ' as character references, for text inside an HTML page.
std::string html_escape(std::string_view text);

}  // namespace sms::gateway::console
