// libFuzzer target: the browser console's request parsing (gateway/console/console_request.h)
// behind the HTTP parser the console uses (Boost.Beast's request_parser with the console's
// header and body limits). The input is the bytes a browser — or anyone — sends:
//   - as an HTTP request: when Beast accepts it, its target is matched against the console's
//     route patterns, its Cookie header and `csrf` query read, the {unit} parameter parsed, and
//     its body handed to every body parser;
//   - as it is, to every body and WebSocket message parser (the JSON side alone).
// Checks: nothing crashes or leaks; a parsed unit is 1-255 and reads back as its text (leading
// zeros aside); a matched parameter is non-empty and has no NUL; a refusal always says why.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/string_body.hpp>

#include "gateway/console/console_request.h"

namespace {

namespace console = sms::gateway::console;
namespace http = boost::beast::http;

// The patterns of gateway/console/console_routes.cpp's table (and the bus monitor's).
constexpr std::string_view kPatterns[] = {
    "/",
    "/servo/{unit}",
    "/login",
    "/commission",
    "/static/{file}",
    "/api/session",
    "/api/servo/{unit}",
    "/api/servo/{unit}/write",
    "/ws/servo/{unit}",
    "/bus/{name}/monitor",
    "/ws/bus/{name}/monitor",
};

void check(bool condition) {
  if (!condition) __builtin_trap();
}

void parse_bodies(std::string_view body) {
  const auto login = console::parse_login(body);
  if (!login) check(!login.error().empty());
  const auto estop = console::parse_estop(body);
  if (!estop) check(!estop.error().empty());
  const auto jog = console::parse_jog_message(body);
  if (!jog) check(!jog.error().empty());
  const auto write = console::parse_field_write(body);
  if (write) check(!write->field.empty() && write->field.size() <= 64);
  if (!write) check(!write.error().empty());
}

void parse_target(std::string_view target) {
  const std::string_view path = console::path_of(target);
  for (const auto pattern : kPatterns) {
    console::PathParams params;
    if (!console::match_path(pattern, path, params)) continue;
    for (const auto name : {"unit", "file", "name"}) {
      const auto value = params.get(name);
      if (!value) continue;
      check(!value->empty() && value->find('\0') == std::string_view::npos);
      if (const auto unit = console::parse_unit(*value)) {
        // Its text is that number (leading zeros aside: /servo/03 is servo 3).
        const std::string_view digits = value->substr(std::min(value->find_first_not_of('0'), value->size()));
        check(*unit >= 1 && std::to_string(*unit) == digits);
      }
    }
  }
  if (const auto csrf = console::query_value(target, "csrf")) check(csrf->find('\0') == std::string::npos);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  parse_bodies(input);
  parse_target(input);
  (void)console::cookie_value(input, "sms_console");
  (void)console::printable(input);

  http::request_parser<http::string_body> parser;
  parser.header_limit(8192);
  parser.body_limit(16384);
  boost::beast::error_code error;
  parser.put(boost::asio::buffer(data, size), error);
  if (!error && parser.is_done()) {
    const auto& request = parser.get();
    parse_target(std::string_view(request.target().data(), request.target().size()));
    if (const auto cookie = request.find(http::field::cookie); cookie != request.end()) {
      (void)console::cookie_value(std::string_view(cookie->value().data(), cookie->value().size()), "sms_console");
    }
    parse_bodies(request.body());
  }
  return 0;
}
