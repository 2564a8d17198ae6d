#pragma once
// What the tool tests share: a simulated bus of one servo, a link to it, and a progress sink
// that says nothing.
#include <gtest/gtest.h>

#include <chrono>
#include <memory>
#include <string>

#include "gateway/tools/tool_link.h"
#include "simulator/simulated_bus.h"

namespace sms::gateway::tool_testing {

inline simulator::BusOptions one_servo(simulator::ServoConfig servo) {
  simulator::BusOptions options;
  options.servos = {servo};
  return options;
}

inline void quiet(const std::string&) {}

inline std::unique_ptr<ServoLink> open_link(const std::string& device, protocol::BusProtocol protocol,
                                            std::uint32_t baud) {
  using namespace std::chrono_literals;
  LinkSettings settings;
  settings.device = device;
  settings.protocol = protocol;
  settings.baud = baud;
  settings.latency = 20ms;  // a pty and the simulator's thread on 2 shared cores, sanitizers on, CI load
  auto link = make_servo_link(settings);
  const auto opened = link->open();
  EXPECT_TRUE(opened) << (opened ? "" : opened.error());
  return link;
}

}  // namespace sms::gateway::tool_testing
