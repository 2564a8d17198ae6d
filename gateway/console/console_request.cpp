#include "gateway/console/console_request.h"

#include <cctype>
#include <charconv>

#include <nlohmann/json.hpp>

namespace sms::gateway::console {

namespace {

using nlohmann::json;

int hex_digit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

// A JSON object from a body, or what is wrong with it. Parsing never throws (allow_exceptions false).
Expected<json> object_of(std::string_view body) {
  json value = json::parse(body.begin(), body.end(), nullptr, false);
  if (value.is_discarded()) return unexpected(std::string("the body is not JSON"));
  if (!value.is_object()) return unexpected(std::string("the body must be a JSON object"));
  return value;
}

Expected<std::string> string_member(const json& object, const char* name, std::size_t max) {
  const auto it = object.find(name);
  if (it == object.end() || !it->is_string()) return unexpected("`" + std::string(name) + "` (a string) is missing");
  const auto& text = it->get_ref<const std::string&>();
  if (text.empty() || text.size() > max) {
    return unexpected("`" + std::string(name) + "` must be 1-" + std::to_string(max) + " characters");
  }
  return text;
}

Expected<std::int64_t> integer_member(const json& object, const char* name) {
  const auto it = object.find(name);
  if (it == object.end()) return unexpected("`" + std::string(name) + "` (an integer) is missing");
  if (it->is_number_integer()) return it->get<std::int64_t>();
  if (it->is_number_float()) {
    const double value = it->get<double>();
    if (value == static_cast<double>(static_cast<std::int64_t>(value)) && value > -1e15 && value < 1e15) {
      return static_cast<std::int64_t>(value);
    }
  }
  return unexpected("`" + std::string(name) + "` must be an integer");
}

}  // namespace

std::optional<std::string_view> PathParams::get(std::string_view name) const {
  for (const auto& [key, value] : values_) {
    if (key == name) return std::string_view(value);
  }
  return std::nullopt;
}

std::string_view path_of(std::string_view target) { return target.substr(0, target.find('?')); }

bool match_path(std::string_view pattern, std::string_view path, PathParams& params) {
  while (!pattern.empty() || !path.empty()) {
    if (pattern.empty() || path.empty() || pattern[0] != '/' || path[0] != '/') return false;
    pattern.remove_prefix(1);
    path.remove_prefix(1);
    const std::string_view pattern_segment = pattern.substr(0, pattern.find('/'));
    const std::string_view path_segment = path.substr(0, path.find('/'));
    pattern.remove_prefix(pattern_segment.size());
    path.remove_prefix(path_segment.size());
    if (pattern_segment.size() > 2 && pattern_segment.front() == '{' && pattern_segment.back() == '}') {
      auto decoded = percent_decode(path_segment);
      if (path_segment.empty() || !decoded) return false;
      params.add(pattern_segment.substr(1, pattern_segment.size() - 2), std::move(*decoded));
    } else if (pattern_segment != path_segment) {
      return false;
    }
  }
  return true;
}

std::string percent_encode(std::string_view text) {
  static constexpr char kHex[] = "0123456789ABCDEF";
  std::string encoded;
  for (const char c : text) {
    const auto byte = static_cast<unsigned char>(c);
    if (std::isalnum(byte) != 0 || c == '-' || c == '.' || c == '_' || c == '~' || c == '/') {
      encoded += c;
    } else {
      encoded += '%';
      encoded += kHex[byte >> 4];
      encoded += kHex[byte & 0x0F];
    }
  }
  return encoded;
}

std::optional<std::string> percent_decode(std::string_view text, bool plus_is_space) {
  std::string out;
  out.reserve(text.size());
  for (std::size_t i = 0; i < text.size(); ++i) {
    char c = text[i];
    if (c == '%') {
      if (i + 2 >= text.size()) return std::nullopt;
      const int high = hex_digit(text[i + 1]);
      const int low = hex_digit(text[i + 2]);
      if (high < 0 || low < 0) return std::nullopt;
      c = static_cast<char>(high * 16 + low);
      i += 2;
    } else if (c == '+' && plus_is_space) {
      c = ' ';
    }
    if (c == '\0') return std::nullopt;
    out.push_back(c);
  }
  return out;
}

std::optional<std::string> query_value(std::string_view target, std::string_view name) {
  const std::size_t mark = target.find('?');
  if (mark == std::string_view::npos) return std::nullopt;
  std::string_view query = target.substr(mark + 1);
  while (!query.empty()) {
    const std::string_view pair = query.substr(0, query.find('&'));
    query.remove_prefix(std::min(query.size(), pair.size() + 1));
    const std::size_t equals = pair.find('=');
    if (pair.substr(0, equals) != name) continue;
    if (equals == std::string_view::npos) return std::string();
    return percent_decode(pair.substr(equals + 1), true);
  }
  return std::nullopt;
}

std::optional<std::string> cookie_value(std::string_view header, std::string_view name) {
  while (!header.empty()) {
    std::string_view pair = header.substr(0, header.find(';'));
    header.remove_prefix(std::min(header.size(), pair.size() + 1));
    while (!pair.empty() && pair.front() == ' ') pair.remove_prefix(1);
    const std::size_t equals = pair.find('=');
    if (equals == std::string_view::npos || pair.substr(0, equals) != name) continue;
    return std::string(pair.substr(equals + 1));
  }
  return std::nullopt;
}

std::optional<std::uint8_t> parse_unit(std::string_view text) {
  if (text.empty() || text.size() > 3) return std::nullopt;
  unsigned value = 0;
  const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (error != std::errc() || end != text.data() + text.size() || value < 1 || value > 255) return std::nullopt;
  return static_cast<std::uint8_t>(value);
}

Expected<LoginRequest> parse_login(std::string_view body) {
  auto object = object_of(body);
  if (!object) return unexpected(object.error());
  auto user = string_member(*object, "user", 64);
  if (!user) return unexpected(user.error());
  auto password = string_member(*object, "password", 1024);
  if (!password) return unexpected(password.error());
  return LoginRequest{std::move(*user), std::move(*password)};
}

Expected<FieldWrite> parse_field_write(std::string_view body) {
  auto object = object_of(body);
  if (!object) return unexpected(object.error());
  auto field = string_member(*object, "field", 64);
  if (!field) return unexpected(field.error());
  auto value = integer_member(*object, "value");
  if (!value) return unexpected(value.error());
  return FieldWrite{std::move(*field), *value};
}

Expected<EstopRequest> parse_estop(std::string_view body) {
  auto object = object_of(body);
  if (!object) return unexpected(object.error());
  const auto it = object->find("latch");
  if (it == object->end() || !it->is_boolean()) return unexpected(std::string("`latch` (true or false) is missing"));
  return EstopRequest{it->get<bool>()};
}

Expected<JogMessage> parse_jog_message(std::string_view text) {
  auto object = object_of(text);
  if (!object) return unexpected(object.error());
  auto type = string_member(*object, "type", 16);
  if (!type) return unexpected(type.error());
  JogMessage message;
  if (*type == "heartbeat") {
    message.kind = JogMessage::Kind::Heartbeat;
  } else if (*type == "release") {
    message.kind = JogMessage::Kind::Release;
  } else if (*type == "torque") {
    const auto it = object->find("on");
    if (it == object->end() || !it->is_boolean()) return unexpected(std::string("`on` (true or false) is missing"));
    message.kind = JogMessage::Kind::Torque;
    message.on = it->get<bool>();
  } else if (*type == "jog") {
    auto mode = string_member(*object, "mode", 16);
    if (!mode) return unexpected(mode.error());
    if (*mode == "position") {
      message.kind = JogMessage::Kind::JogPosition;
    } else if (*mode == "speed") {
      message.kind = JogMessage::Kind::JogSpeed;
    } else {
      return unexpected("`mode` must be position or speed, got " + printable(*mode));
    }
    auto value = integer_member(*object, "value");
    if (!value) return unexpected(value.error());
    message.value = *value;
  } else {
    return unexpected("unknown message type " + printable(*type) + " (heartbeat, jog, release, torque)");
  }
  return message;
}

std::string printable(std::string_view text, std::size_t max) {
  std::string out;
  for (const char c : text.substr(0, max)) {
    // Printable ASCII as it is ('/' in a path, quotes in a name); control characters (a forged
    // line in the log) and bytes past ASCII become '?'.
    const bool plain = c >= 0x20 && c <= 0x7E;
    out.push_back(plain ? c : '?');
  }
  if (text.size() > max) out += "...";
  return out;
}

std::string html_escape(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (const char c : text) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      case '\'': out += "&#39;"; break;
      default: out.push_back(c);
    }
  }
  return out;
}

}  // namespace sms::gateway::console
