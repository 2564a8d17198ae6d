// The one role gate of every way in (gateway/service/access_gate.h): each refusal's exception, its
// log line (at most one a second per gate) and its count, the same whether a way in puts a
// RoleGate in front of the router (a Modbus/TCP Security connection, an RTU port) or asks the
// gate itself (the console, the Sparkplug node). The RTU port's own use of it is tested in
// tests/gateway/rtu_slave/.
#include <gtest/gtest.h>

#include <memory>
#include <vector>

#include "gateway/service/access_gate.h"
#include "tests/gateway/service/service_plant.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using config::Role;
using Pdu = std::vector<std::uint8_t>;
using testing::LogCapture;
using testing::write_register;

// What reached the router behind a gate, and what the client was answered.
struct Router final : RequestHandler {
  void handle(std::uint8_t, std::span<const std::uint8_t> pdu, Reply reply) override {
    ++handled;
    reply.send(Bytes(pdu.begin(), pdu.end()));  // an FC06 answer echoes its request
  }
  int handled = 0;
};
struct Answers final : Reply::Target {
  void deliver(std::uint64_t, Bytes pdu) override { got.push_back(std::move(pdu)); }
  std::vector<Bytes> got;
};

class Gate : public ::testing::Test {
 protected:
  // One request through a RoleGate of its own (as each TLS connection has); its answer.
  Bytes through_role_gate(Role role, std::uint8_t unit, const Pdu& pdu) {
    RoleGate gate(policy_, role, "rtu slave /dev/ttyUSB9", &refusals_, router_);
    auto answers = std::make_shared<Answers>();
    gate.handle(unit, pdu, Reply(answers, 1));
    return answers->got.empty() ? Bytes{} : answers->got.front();
  }

  testing::ServicePlant plant_;
  const RolePolicy& policy_ = plant_.policy;
  RefusalCounter refusals_;
  Router router_;
  LogCapture log_;
};

TEST_F(Gate, EachRefusalIsAnsweredWithItsExceptionLoggedAndCountedAndNeverReachesTheRouter) {
  // A function class the role lacks: 0x01.
  EXPECT_EQ(through_role_gate(Role::Read, 1, write_register(42, 2048)), (Bytes{0x86, 0x01}));
  EXPECT_TRUE(
      log_.contains("rtu slave /dev/ttyUSB9: unit 1 FC06 refused (0x01) for role read: role read may only read"))
      << log_.text();
  EXPECT_EQ(through_role_gate(Role::None, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}), (Bytes{0x83, 0x01}));
  EXPECT_TRUE(log_.contains("unit 1 FC03 refused (0x01) for role none: the connection has no role")) << log_.text();
  EXPECT_EQ(through_role_gate(Role::Operate, 10, {0x08, 0x00, 0x01, 0x00, 0x00}), (Bytes{0x88, 0x01}));
  EXPECT_TRUE(log_.contains("functions of unknown effect need role engineer")) << log_.text();
  // An address the role may not write: 0x02.
  EXPECT_EQ(through_role_gate(Role::Operate, 1, write_register(13, 70)), (Bytes{0x86, 0x02}));
  EXPECT_TRUE(
      log_.contains("unit 1 FC06 refused (0x02) for role operate: writes EEPROM field max_temperature (13), "
                    "which needs role engineer"))
      << log_.text();
  EXPECT_EQ(through_role_gate(Role::Operate, 1, write_register(40, 128)), (Bytes{0x86, 0x02}));
  EXPECT_TRUE(log_.contains("mid-point calibration (torque_enable (40) := 128) needs role engineer")) << log_.text();

  EXPECT_EQ(router_.handled, 0);
  EXPECT_EQ(refusals_.of(Role::Read), 1u);
  EXPECT_EQ(refusals_.of(Role::None), 1u);
  EXPECT_EQ(refusals_.of(Role::Operate), 3u);
  EXPECT_EQ(refusals_.total(), 5u);
}

TEST_F(Gate, WhatTheRoleMayDoGoesToTheRouterUncountedAndUnlogged) {
  EXPECT_EQ(through_role_gate(Role::Operate, 1, write_register(42, 2048)), Bytes(write_register(42, 2048)));
  EXPECT_EQ(through_role_gate(Role::Read, 1, {0x03, 0x00, 0x2A, 0x00, 0x01}), (Bytes{0x03, 0x00, 0x2A, 0x00, 0x01}));
  EXPECT_EQ(through_role_gate(Role::Engineer, 1, write_register(13, 70)), Bytes(write_register(13, 70)));
  EXPECT_EQ(router_.handled, 3);
  EXPECT_EQ(refusals_.total(), 0u);
  EXPECT_FALSE(log_.contains("refused")) << log_.text();
}

TEST_F(Gate, AWayInThatAsksTheGateItselfGetsTheSameExceptionAndWordsAndNamesItsClient) {
  // The console (a user per request, no counter of its own) and the Sparkplug node ask check().
  AccessGate console(policy_, "console");
  const auto refusal = console.check(Role::Operate, 1, write_register(13, 70), "alice");
  ASSERT_TRUE(refusal);
  EXPECT_EQ(refusal->exception, ModbusException::IllegalDataAddress);
  EXPECT_EQ(refusal->answer(write_register(13, 70)), through_role_gate(Role::Operate, 1, write_register(13, 70)));
  EXPECT_EQ(refusal->text(),
            "refused for role operate: writes EEPROM field max_temperature (13), which needs role engineer");
  EXPECT_TRUE(
      log_.contains("console (alice): unit 1 FC06 refused (0x02) for role operate: writes EEPROM field "
                    "max_temperature (13), which needs role engineer"))
      << log_.text();
  EXPECT_FALSE(console.check(Role::Operate, 1, write_register(42, 2048), "alice"));
  EXPECT_EQ(refusals_.of(Role::Operate), 1u);  // the RoleGate's; the console's gate counts nowhere
}

TEST_F(Gate, AClientRefusedCyclicallyIsCountedEveryTimeAndLoggedOnceASecond) {
  RoleGate gate(policy_, Role::Read, "rtu slave /dev/ttyUSB9", &refusals_, router_);
  auto answers = std::make_shared<Answers>();
  for (std::uint64_t i = 0; i < 5; ++i) gate.handle(1, write_register(42, 2048), Reply(answers, i));
  EXPECT_EQ(answers->got, std::vector<Bytes>(5, Bytes{0x86, 0x01}));
  EXPECT_EQ(refusals_.of(Role::Read), 5u);
  const std::string text = log_.text();
  std::size_t lines = 0;
  for (std::size_t at = text.find("refused (0x01)"); at != std::string::npos;
       at = text.find("refused (0x01)", at + 1)) {
    ++lines;
  }
  EXPECT_EQ(lines, 1u) << text;
}

}  // namespace
}  // namespace sms::gateway
