#pragma once
// The spellings of the configuration's enumerations, as data: config.cpp prints them, the
// loader parses them and lists them in its errors. Private to config/.
#include <array>
#include <optional>
#include <string>
#include <string_view>

#include "config/config.h"

namespace sms::config::detail {

template <typename E>
struct Named {
  std::string_view name;
  E value;
};

inline constexpr std::array<Named<Parity>, 3> kParityNames{{
    {"none", Parity::None},
    {"even", Parity::Even},
    {"odd", Parity::Odd},
}};

inline constexpr std::array<Named<RtsMode>, 3> kRtsNames{{
    {"none", RtsMode::None},
    {"up", RtsMode::Up},
    {"down", RtsMode::Down},
}};

// modbus_rtu_slave's echo: auto, or a boolean (on/true/yes: the adapter echoes).
inline constexpr std::array<Named<RtuEcho>, 3> kRtuEchoNames{{
    {"auto", RtuEcho::Auto},
    {"on", RtuEcho::On},
    {"off", RtuEcho::Off},
}};

inline constexpr std::array<Named<Profile>, 2> kProfileNames{{
    {"native", Profile::Native},
    {"smsmb", Profile::Smsmb},
}};

inline constexpr std::array<Named<LogLevel>, 7> kLogLevelNames{{
    {"trace", LogLevel::Trace},
    {"debug", LogLevel::Debug},
    {"info", LogLevel::Info},
    {"warn", LogLevel::Warn},
    {"error", LogLevel::Error},
    {"critical", LogLevel::Critical},
    {"off", LogLevel::Off},
}};

inline constexpr std::array<Named<LogFormat>, 2> kLogFormatNames{{
    {"plain", LogFormat::Plain},
    {"json", LogFormat::Json},
}};

inline constexpr std::array<Named<modbus_map::ByteOrder>, 2> kByteOrderNames{{
    {"low-first", modbus_map::ByteOrder::LowFirst},
    {"high-first", modbus_map::ByteOrder::HighFirst},
}};

inline constexpr std::array<Named<WatchdogFeed>, 2> kWatchdogFeedNames{{
    {"any_write", WatchdogFeed::AnyWrite},
    {"heartbeat_register", WatchdogFeed::HeartbeatRegister},
}};

inline constexpr std::array<Named<Role>, 4> kRoleNames{{
    {"none", Role::None},
    {"read", Role::Read},
    {"operate", Role::Operate},
    {"engineer", Role::Engineer},
}};

inline constexpr std::array<Named<StartAction>, 3> kStartActionNames{{
    {"keep", StartAction::Keep},
    {"hold", StartAction::Hold},
    {"torque_off", StartAction::TorqueOff},
}};

inline constexpr std::array<Named<modbus_map::StopAction>, 3> kStopActionNames{{
    {"hold", modbus_map::StopAction::Hold},
    {"torque_off", modbus_map::StopAction::TorqueOff},
    {"none", modbus_map::StopAction::None},
}};

template <typename E, std::size_t N>
constexpr std::string_view name_of(const std::array<Named<E>, N>& names, E value) {
  for (const auto& entry : names) {
    if (entry.value == value) return entry.name;
  }
  return "unknown";
}

template <typename E, std::size_t N>
constexpr std::optional<E> value_of(const std::array<Named<E>, N>& names, std::string_view name) {
  for (const auto& entry : names) {
    if (entry.name == name) return entry.value;
  }
  return std::nullopt;
}

// "none, even, odd" for error messages.
template <typename E, std::size_t N>
std::string names_text(const std::array<Named<E>, N>& names) {
  std::string text;
  for (const auto& entry : names) {
    if (!text.empty()) text += ", ";
    text += entry.name;
  }
  return text;
}

}  // namespace sms::config::detail
