#pragma once
// The one door of every way in (docs/SECURITY.md "Roles", docs/RTU_PANELS.md, docs/CONSOLE.md,
// docs/MQTT.md): a request's role is checked against the role policy before the unit router sees
// it; a refusal is answered with its exception (0x01 or 0x02), logged as a warning at most once
// a second per gate (a client writing cyclically what its role may not would fill the log) and
// counted. Each way in keeps only how it finds the role: a client certificate (Modbus/TCP
// Security), the port's `role` (an upstream RTU port), the user's session (the console),
// mqtt.role (the Sparkplug node's commands).
//
//   RoleGate gate(policy, Role::Operate, "rtu slave /dev/ttyUSB1", &refusals, router);
//   gate.handle(unit, pdu, reply);  // the router, or the refusal's exception answer
//
//   AccessGate gate(policy, "console");  // a way in whose requests carry roles of their own
//   if (const auto refusal = gate.check(who.role, unit, pdu, who.name)) answer refusal->text();
#include <array>
#include <atomic>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "config/config.h"
#include "gateway/service/modbus_request.h"
#include "gateway/service/rate_limited_log.h"
#include "gateway/service/request_handler.h"
#include "gateway/service/role_policy.h"

namespace sms::gateway {

// The requests a way in's gates refused, by the role that lacked the right. Counted on the gates'
// thread, read on any (/metrics).
class RefusalCounter {
 public:
  void count(config::Role role);
  std::uint64_t of(config::Role role) const;
  std::uint64_t total() const;

 private:
  std::array<std::atomic<std::uint64_t>, 4> by_role_{};  // by config::Role
};

// Why a gate refused a request, in the words every way in answers with.
struct GateRefusal {
  config::Role role = config::Role::None;
  ModbusException exception = ModbusException::IllegalFunction;  // 0x01 or 0x02
  std::string reason;  // the policy's: "writes EEPROM field id (5), which needs role engineer"

  // "refused for role operate: writes EEPROM field id (5), which needs role engineer"
  std::string text() const;
  // The exception response to `pdu`.
  Bytes answer(std::span<const std::uint8_t> pdu) const;
};

class AccessGate {
 public:
  // `way`: who asks through this gate, first in its log lines ("rtu slave /dev/ttyUSB1");
  // `counter`: where its refusals are counted, nullptr where the way in counts them among figures
  // of its own (the Sparkplug node's refused commands). `policy` and `counter` must outlive the
  // gate. One thread at a time: the log line's limit is not locked.
  AccessGate(const RolePolicy& policy, std::string way, RefusalCounter* counter = nullptr);

  // nullopt: `role` may make the request. Else the refusal, logged and counted. `who` names the
  // client where one way in serves several ("alice"), in the log line.
  std::optional<GateRefusal> check(config::Role role, std::uint8_t unit, std::span<const std::uint8_t> pdu,
                                   std::string_view who = {});

 private:
  const RolePolicy& policy_;
  const std::string way_;
  RefusalCounter* const counter_;
  RateLimitedLog log_;
};

// A way in whose requests all have one role (a Modbus/TCP Security connection, an RTU port):
// the gate in front of `next` (the unit router). A refused request never reaches `next`.
class RoleGate final : public RequestHandler {
 public:
  RoleGate(const RolePolicy& policy, config::Role role, std::string way, RefusalCounter* counter, RequestHandler& next);

  void handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) override;

 private:
  AccessGate gate_;
  const config::Role role_;
  RequestHandler& next_;
};

}  // namespace sms::gateway
