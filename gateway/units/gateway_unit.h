#pragma once
// The gateway's own Modbus unit (255 by default; docs/PLC_GUIDE.md "The gateway unit"):
// - input registers 0-2 version, 3-4 uptime s, 5/6 buses/servos, 100 + 20·n the facts of bus n;
// - coil 0: writing 1 sends ACTION on every bus (runs every staged REG WRITE at once);
// - coils 1-2, discrete inputs 0-4, input registers 10-15 and 100 + 20·n + 10..19, holding
//   registers 1000 + n: the safety rules (docs/PLC_GUIDE.md "Safety");
// - holding registers of the configured sync groups: one register per member; a write of a
//   group's registers becomes one SYNC WRITE frame per bus, read gives the members' live values;
//   a group with `move_time` has the move time after its members, and a non-zero move time makes
//   its goals a timed move (every axis arrives together);
// - input registers 2000 + 10·g: sync group g's timed moves.
// Runs on the io thread like the rest of the TCP side; bus completions come back through PostFn.
#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_engine.h"
#include "gateway/bus/bus_join.h"
#include "gateway/service/modbus_request.h"
#include "gateway/service/rate_limited_log.h"
#include "gateway/service/request_handler.h"
#include "gateway/service/unit_catalog.h"
#include "gateway/units/no_jump.h"
#include "gateway/units/safety.h"
#include "modbus_map/control_table.h"
#include "modbus_map/register_map.h"
#include "modbus_map/timed_move.h"

namespace sms::gateway {

// Register offsets inside bus n's block of input registers (100 + 20·n).
namespace gateway_unit_layout {
inline constexpr std::uint16_t kVersion = 0;  // 0-2 major, minor, patch
inline constexpr std::uint16_t kUptime = 3;   // 3-4 seconds, high word first
inline constexpr std::uint16_t kBusCount = 5;
inline constexpr std::uint16_t kServoCount = 6;
inline constexpr std::uint16_t kFirstBusBlock = 100;
inline constexpr std::uint16_t kBusBlockSize = 20;
inline constexpr std::uint16_t kActionCoil = 0;
// Safety (docs/PLC_GUIDE.md "Safety"): coil 1 e-stop latch (1 latches and stops every bus, 0 resets), coil 2
// watchdogs (reads 1 while any is tripped; 0 re-arms them); discrete inputs 0 e-stop latched,
// 1 any watchdog tripped, 2 motion blocked on any bus.
inline constexpr std::uint16_t kEStopCoil = 1;
inline constexpr std::uint16_t kWatchdogCoil = 2;
// 3 a safe stop is owed to some servo (it could not be delivered yet), 4 the safety state is
// not persisted (a save to state_dir failed and none has succeeded since: docs/SAFETY.md).
inline constexpr std::uint16_t kStateNotPersistedInput = 4;
inline constexpr std::uint16_t kCoilCount = 3;
inline constexpr std::uint16_t kDiscreteInputCount = 5;
// Input registers 10 e-stop latched, 11-12 e-stops (32-bit), 13 servos owed a safe stop (every
// bus), 14-15 safe stops that failed (32-bit, every bus).
inline constexpr std::uint16_t kEStopLatched = 10;
inline constexpr std::uint16_t kEStopCount = 11;
inline constexpr std::uint16_t kOwedStops = 13;
inline constexpr std::uint16_t kFailedStops = 14;
// Input register 16: servos offline because they answer late (probed only), every bus
// (docs/DECISIONS.md "A servo that answers late"; each servo's own reason is its input register 1008).
inline constexpr std::uint16_t kLateServos = 16;
// Inside bus n's block (100 + 20·n): 10 watchdog state (0 off, 1 armed, 2 running, 3 tripped),
// 11 ms since the last feed (65535: never or longer), 12-13 trips, 14 timeout ms, 15 cause of
// the last safe stop (0 none, 1 watchdog, 2 e-stop, 3 on_start, 4 on_stop, 5 commissioning), 16-17 its latency µs
// (last feed or request -> frames on the wire; 0 after a stop that failed), 18 motion blocked,
// 19 servos of the bus owed a safe stop.
inline constexpr std::uint16_t kWatchdogState = 10;
// Sync group g's input registers (docs/PLC_GUIDE.md "Timed group moves"), at 2000 + 10·g in the
// order of `sync_groups`: 0 moving (1 while a timed move runs), 1 time left ms, 2 largest distance
// to go (position units, from the poll cache), 3 the last timed move (0 none, 1 as asked,
// 2 stretched, 3 refused), 4 the unit that limits it, 5 that unit's shortest time ms, 6 the move
// time used ms.
inline constexpr std::uint16_t kFirstGroupBlock = 2000;
inline constexpr std::uint16_t kGroupBlockSize = 10;
enum class GroupRegister : std::uint16_t {
  Moving = 0,
  TimeLeft = 1,
  DistanceToGo = 2,
  LastMove = 3,
  LimitingUnit = 4,
  ShortestTime = 5,
  MoveTime = 6,
};
enum class TimedMoveResult : std::uint16_t { None = 0, AsAsked = 1, Stretched = 2, Refused = 3 };
}  // namespace gateway_unit_layout

// What the gateway unit shows about one bus (input registers 100 + 20·n ...).
struct BusFacts {
  bool up = false;
  std::uint32_t baud = 0;
  std::uint32_t last_poll_cycle_us = 0;
  std::size_t servos_online = 0;
  std::uint64_t frames_ok = 0;
  std::uint64_t timeouts = 0;
  std::uint64_t checksum_errors = 0;  // checksum and framing errors
};
BusFacts bus_facts(const BusEngine& engine);

class GatewayUnit {
 public:
  // `engines[i]` runs config.buses[i]; the sync groups' members' maps come from `catalog`, which
  // must outlive the unit. Throws std::invalid_argument when a sync group names a unit or field
  // the configuration does not have (the config loader rejects those first).
  GatewayUnit(const config::Config& config, const UnitCatalog& catalog, std::vector<BusEngine*> engines, PostFn post,
              SafetySupervisor& safety,
              std::chrono::steady_clock::time_point started = std::chrono::steady_clock::now());

  void handle(const Request& request, const Reply& reply);

  // The input registers [address, address + count), or nullopt when the range leaves them.
  std::optional<std::vector<std::uint16_t>> input_registers(std::uint16_t address, std::uint16_t count) const;

 private:
  struct SyncMember {
    std::uint8_t unit_id = 0;
    std::size_t bus = 0;
    std::uint8_t servo_id = 0;
    const modbus_map::FieldSpec* field = nullptr;
    const modbus_map::RegisterMap* map = nullptr;  // native map of the member's table and byte order: value rules
    bool read_only = false;
    std::optional<std::uint8_t> response_level;  // as configured; empty: as read from the servo
  };
  // What the group's input registers show of its last timed move.
  struct TimedMoveState {
    gateway_unit_layout::TimedMoveResult result = gateway_unit_layout::TimedMoveResult::None;
    std::uint8_t limiting_unit = 0;
    std::chrono::milliseconds shortest{0};
    std::chrono::milliseconds used{0};
    std::optional<std::chrono::steady_clock::time_point> ends;  // when the axes arrive (plan)
  };
  struct SyncGroup {
    std::string name;
    std::uint16_t start = 0;
    std::vector<SyncMember> members;
    bool has_move_time = false;  // register start + members.size() is the move time (ms)
    bool stretch = false;
    std::uint16_t move_time_ms = 0;
    std::vector<std::optional<std::int32_t>> last_goals;  // per member, in servo units
    TimedMoveState timed;
  };
  // One member's value of a group write.
  struct MemberWrite {
    const SyncMember* member = nullptr;
    std::size_t index = 0;  // in its group
    std::uint16_t value = 0;
  };
  struct Frame {
    std::size_t bus;
    BusOp op;
  };

  const SyncMember* sync_member_at(std::uint16_t address) const;
  SyncGroup* group_of(const SyncMember* member);
  SyncGroup* move_time_group_at(std::uint16_t address);
  std::vector<std::uint16_t> group_input_registers() const;
  void record_goal(SyncGroup& group, const MemberWrite& write) const;
  // The group's timed move of `writes` (docs/PLC_GUIDE.md "Timed group moves").
  void timed_move(SyncGroup& group, std::vector<MemberWrite> writes, std::uint16_t move_time_ms,
                  const WriteRegistersRequest& request, const Reply& reply, std::function<void(const Reply&)> after);
  void plan_and_send(SyncGroup& group, std::vector<MemberWrite> writes, std::vector<modbus_map::TimedMoveSpec> specs,
                     std::vector<std::int32_t> present, std::uint16_t move_time_ms, std::uint8_t function,
                     const Reply& reply, std::function<void(const Reply&)> after);
  // Every refusal of a timed move shows in its group's registers: result 3 (refused), the used
  // time 0; what still runs from an earlier move shows in moving and distance to go.
  static void refuse_timed_move(SyncGroup& group);
  // Sends the frames (after the holds `switched_on` needs), feeds the watchdogs of `buses` once
  // all are carried out, then runs `after`, or runs `failed` and answers the failure.
  void send_frames(std::vector<Frame> frames, std::vector<HoldTarget> switched_on, std::vector<std::size_t> buses,
                   std::uint8_t function, const Reply& reply, std::function<void(const Reply&)> after,
                   const std::function<void()>& failed = {});
  void read_sync_registers(std::uint8_t function, std::uint16_t address, std::uint16_t count, const Reply& reply);
  void write_sync_registers(const WriteRegistersRequest& request, const Reply& reply,
                            std::function<void(const Reply&)> after);
  void write_coil(const WriteBitsRequest& request, const Reply& reply);
  void write_action_coil(const WriteBitsRequest& request, const Reply& reply);
  void write_estop_coil(const WriteBitsRequest& request, const Reply& reply);
  std::vector<bool> coils() const;
  // Holding registers 1000 + n: bus n's watchdog heartbeat.
  bool heartbeat_range(std::uint16_t address, std::uint16_t count) const;
  void read_heartbeats(std::uint8_t function, std::uint16_t address, std::uint16_t count, const Reply& reply) const;
  void write_heartbeats(const WriteRegistersRequest& request);

  std::vector<BusEngine*> engines_;
  std::vector<SyncGroup> groups_;
  std::size_t servo_count_ = 0;
  PostFn post_;
  SafetySupervisor& safety_;
  MotionRefusalLog refusal_log_;
  RateLimitedLog failure_log_;  // writes not done (an offline servo written cyclically), once a second
  std::chrono::steady_clock::time_point started_;
};

}  // namespace sms::gateway
