#pragma once
// A small plant as real processes: an `arm` feetech bus (sms-sim: sts 1-3, sms1 4-5) and a
// `base` d55d bus (sms-sim: d55d 1-2 at 115 200), and sms-gateway serving both with every
// table and both profiles on its units:
//   unit 1, 2  sts native      unit 3  sts smsmb      unit 4  sms1 native   unit 5  sms1 smsmb
//   unit 11, 12  d55d native
//   gateway unit 255: sync group arm_goals (goal_position of 1, 2, 4) at holding 0-2,
//                     base_speeds (run_speed of 11, 12) at holding 10-11
#include <memory>
#include <string>

#include "tests/support/processes.h"

namespace sms::e2e {

using namespace ::sms::test;  // the toolkit: tests/support

inline constexpr const char* kPlantConfig = R"(
modbus_tcp: {listen: "127.0.0.1:5020", max_connections: 64, request_queue_depth: @QUEUE@}
buses:
  - {name: arm, device: "@ARM@", protocol: feetech, baud: 1000000, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: @TIMEOUT@, retries: 1}
  - {name: base, device: "@BASE@", protocol: d55d, baud: 115200, poll_period_ms: 10,
     offline_probe_period_ms: 100, response_timeout_ms: @TIMEOUT@, retries: 1}
servos:
  - {unit: 1, bus: arm, id: 1, table: sts}
  - {unit: 2, bus: arm, id: 2, table: sts}
  - {unit: 3, bus: arm, id: 3, table: sts, profile: smsmb}
  - {unit: 4, bus: arm, id: 4, table: sms1}
  - {unit: 5, bus: arm, id: 5, table: sms1, profile: smsmb}
  - {unit: 11, bus: base, id: 1, table: d55d}
  - {unit: 12, bus: base, id: 2, table: d55d}
sync_groups:
  - {name: arm_goals, field: goal_position, members: [1, 2, 4], holding_register_start: 0}
  - {name: base_speeds, field: run_speed, members: [11, 12], holding_register_start: 10}
)";

struct PlantOptions {
  int request_queue_depth = 64;
  // Generous: these tests are about behaviour, and a loaded CI machine can delay the simulator's
  // answers by tens of milliseconds (a timeout would mark a healthy servo offline).
  int response_timeout_ms = 100;
};

class Plant {
 public:
  explicit Plant(PlantOptions options = {})
      : arm_(dir_, "arm",
             {"--servo", "1:sts", "--servo", "2:sts", "--servo", "3:sts", "--servo", "4:sms1", "--servo", "5:sms1"}),
        base_(dir_, "base", {"--servo", "1:d55d:d55d:115200", "--servo", "2:d55d:d55d:115200"}) {
    std::string yaml = substitute(kPlantConfig, "@ARM@", arm_.pty());
    yaml = substitute(yaml, "@BASE@", base_.pty());
    yaml = substitute(yaml, "@QUEUE@", std::to_string(options.request_queue_depth));
    yaml = substitute(yaml, "@TIMEOUT@", std::to_string(options.response_timeout_ms));
    gateway_ = std::make_unique<GatewayProcess>(GatewayProcess::with_config(dir_, yaml, 2));
  }

  std::uint16_t port() const { return gateway_->port(); }
  SimProcess& arm() { return arm_; }
  SimProcess& base() { return base_; }
  // The simulator holding `unit`'s servo.
  SimProcess& sim_of(int unit) { return unit >= 11 ? base_ : arm_; }
  GatewayProcess& gateway() { return *gateway_; }
  const TempDir& dir() const { return dir_; }

 private:
  TempDir dir_;
  SimProcess arm_;
  SimProcess base_;
  std::unique_ptr<GatewayProcess> gateway_;
};

}  // namespace sms::e2e
