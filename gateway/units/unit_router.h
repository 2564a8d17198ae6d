#pragma once
// Modbus unit id -> what answers it (docs/PLC_GUIDE.md "Units", "A servo unit"):
// - a servo unit: (bus engine, servo id, register map of its table/profile/byte order,
//   whether it answers writes). FC03/FC23-read/FC01 read live through register plans
//   (Priority::ClientRead); FC04/FC02 are served from the poll cache and the gateway's own
//   facts (1000-1008) without bus traffic; FC05/06/15/16/23-write become WriteOps
//   (Priority::ClientWrite, REG WRITE for 512 + a) answered once the servo acknowledged them;
// - a passthrough unit (modbus-rtu slave without a table): the PDU forwarded as it is;
// - the gateway unit (GatewayUnit);
// - anything else: 0x0A.
// Runs on the io thread; bus completions come back through PostFn.
#include <array>
#include <cstdint>
#include <memory>
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
#include "gateway/units/gateway_unit.h"
#include "gateway/units/safety.h"
#include "modbus_map/register_map.h"

namespace sms::gateway {

// Input registers 1000-1007 and discrete inputs 1000-1008 of a servo unit: facts the gateway
// keeps about the servo (no table uses these addresses).
namespace servo_facts_layout {
inline constexpr std::uint16_t kFirstRegister = 1000;
inline constexpr std::uint16_t kRegisterCount = 9;  // 1000 .. 1008
inline constexpr std::uint16_t kFirstBit = 1000;    // 1000 + b: bit b of register 1000
inline constexpr std::uint16_t kOnlineBit = 1008;
// Offsets inside the block: 0 status byte, 1 online, 2 cache age ms, 3 identity, 4-5 replies ok
// and 6-7 timeouts (32-bit, high word first), 8 why it is offline (OfflineReason).
inline constexpr std::size_t kStatus = 0;
inline constexpr std::size_t kOnline = 1;
inline constexpr std::size_t kCacheAge = 2;
inline constexpr std::size_t kIdentity = 3;
inline constexpr std::size_t kRepliesOk = 4;
inline constexpr std::size_t kTimeouts = 6;
inline constexpr std::size_t kOfflineReason = 8;
}  // namespace servo_facts_layout

// Whether a servo of `table` at `response_level` answers unicast WRITE / REG WRITE (docs/PROTOCOL.md §2.1
// and §2.2 address 8: 0 = only READ and PING; §2.3 address 16: 2 = all but broadcast).
bool writes_answered(modbus_map::TableId table, std::uint8_t response_level);

// What the facts registers show, gathered from the poll cache.
struct ServoFacts {
  std::uint8_t last_status = 0;
  bool online = false;
  std::optional<std::chrono::milliseconds> cache_age;  // nullopt: never polled
  std::uint16_t identity = 0;                          // model, else firmware, as read at discovery
  std::uint64_t replies_ok = 0;
  std::uint64_t timeouts = 0;
  OfflineReason offline_reason = OfflineReason::None;
};
// Registers 1000-1008 from the facts: saturating age (65535 also before the first poll),
// 32-bit counters high word first (they wrap).
std::array<std::uint16_t, servo_facts_layout::kRegisterCount> servo_fact_registers(const ServoFacts& facts);

struct ServoUnit {
  std::uint8_t unit_id = 0;
  std::size_t bus_index = 0;
  BusEngine* engine = nullptr;
  std::uint8_t servo_id = 0;
  const modbus_map::RegisterMap& map;  // the unit's, from the UnitCatalog
  modbus_map::BusRange poll_block;     // what the engine polls into the cache for this servo
  // The response level from the configuration; without one, the level discovery read from
  // the servo (poll cache), else the table's factory behaviour (writes answered).
  std::optional<std::uint8_t> configured_response_level;
  bool read_only = false;
  std::string label;  // "unit 3 (bus arm, servo 3)" for logs
};

// Whether a WRITE to this unit's servo waits for its answer: the configured response level,
// else the level discovery read from the servo, else yes (every table's factory level).
bool expects_write_reply(const ServoUnit& unit);
// Whether servo `servo_id` on `engine` answers unicast writes: its configured response level, else
// the one read from it (the poll cache), else yes (every table's factory level answers writes).
// The one rule for servo units, sync groups and owed safe stops.
bool answers_writes(modbus_map::TableId table, std::optional<std::uint8_t> configured_level, const BusEngine& engine,
                    std::uint8_t servo_id);

// A unit on a modbus-rtu bus without a table: its PDUs are forwarded to the slave unchanged
// and its answers (exceptions included) come back unchanged.
struct PassthroughUnit {
  std::uint8_t unit_id = 0;
  BusEngine* engine = nullptr;
  std::uint8_t slave = 0;
  std::size_t bus_index = 0;
  bool read_only = false;  // read_only_refusal() decides, as for servo units
  std::string label;
};

class UnitRouter : public RequestHandler {
 public:
  // `engines[i]` runs config.buses[i] (the engine's settings give each servo's poll block);
  // the servo units' register maps come from `catalog`, which must outlive the router.
  // Every write passes `safety` (docs/PLC_GUIDE.md "Safety"): a motion write is refused (0x04) while the
  // e-stop is latched or the watchdog tripped, and a write the gateway carried out (answered
  // without an exception) feeds the bus's watchdog — one rule for servo and passthrough units.
  UnitRouter(const config::Config& config, const UnitCatalog& catalog, std::vector<BusEngine*> engines, PostFn post,
             SafetySupervisor& safety);

  void handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) override;

  const ServoUnit* servo_unit(std::uint8_t unit_id) const;
  std::uint8_t gateway_unit_id() const { return gateway_unit_id_; }

  // Why a write to `unit` was answered 0x04, in words for a person (the console, the Sparkplug
  // node's Last Command); Modbus clients get only the code and read the rule from unit 255.
  struct RefusalReason {
    std::string text;
    bool safety_rule = false;  // a safety rule refuses motion to the unit now; else the servo did
  };
  // The rule that refuses motion to it now (SafetySupervisor::motion_refusal, the one source of
  // the rules), else the servo itself, with the faults of its last status byte. Any thread.
  RefusalReason refusal_reason(const ServoUnit& unit) const;

 private:
  void dispatch(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, const Reply& reply);
  void handle_servo(const ServoUnit& unit, const Request& request, const Reply& reply);
  void forward(const PassthroughUnit& unit, std::span<const std::uint8_t> pdu, const Reply& reply);
  // The safety rules' admission of a motion write on `bus_index` (servo and passthrough units
  // alike): its epoch, or nullopt after answering 0x04 (the refusal logged at most once a
  // second, naming `what`).
  std::optional<MotionEpoch> admit_motion(std::size_t bus_index, const std::string& what, std::uint8_t function,
                                          const Reply& reply);
  // One rule for servo and passthrough units (read_only_refusal): true when it answered.
  bool refused_as_read_only(bool read_only, const std::string& label, std::uint8_t function, const Reply& reply) const;
  void read_holding(const ServoUnit& unit, std::uint8_t function, std::uint16_t start, std::uint16_t count,
                    const Reply& reply);
  void read_input(const ServoUnit& unit, const ReadRegistersRequest& request, const Reply& reply);
  void read_coils(const ServoUnit& unit, const ReadBitsRequest& request, const Reply& reply);
  void read_discrete(const ServoUnit& unit, const ReadBitsRequest& request, const Reply& reply);
  // The safety rules, then the plan's frames one after another (a refusal stops the rest), then
  // `after`: a motion write is refused while motion is blocked; a write that may enable motion
  // (torque on, d55d wake or brake release, a drive change) gets the hold of the goal block first
  // where it needs one ("no jump on enable", gateway/units/no_jump.h).
  void run_writes(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan, const Reply& reply,
                  std::function<void(const Reply&)> after);
  void run_admitted_writes(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan, MotionEpoch epoch,
                           const Reply& reply, std::function<void(const Reply&)> after);
  // Holds the servo's goal block where `plan` enables it (gateway/units/no_jump.h), then runs `plan`.
  void hold_then_enable(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan, MotionEpoch epoch,
                        const Reply& reply, std::function<void(const Reply&)> after);
  // Live reads of plan.reads, in order; `then` gets the replies' bytes.
  void run_reads(const ServoUnit& unit, std::uint8_t function, const modbus_map::ReadPlan& plan, const Reply& reply,
                 std::function<void(std::vector<protocol::Bytes>)> then);
  // Copies plan.reads out of the poll cache; nullopt after answering the failure.
  std::optional<std::vector<protocol::Bytes>> copy_from_cache(const ServoUnit& unit, std::uint8_t function,
                                                              const modbus_map::ReadPlan& plan, const Reply& reply);
  ServoFacts facts_of(const ServoUnit& unit) const;
  void refuse(const ServoUnit& unit, std::uint8_t function, const modbus_map::MapError& error,
              const Reply& reply) const;

  std::array<std::unique_ptr<ServoUnit>, 256> units_{};
  std::array<std::unique_ptr<PassthroughUnit>, 256> passthrough_{};
  std::uint8_t gateway_unit_id_ = 255;
  std::unique_ptr<GatewayUnit> gateway_unit_;
  PostFn post_;
  SafetySupervisor& safety_;
  MotionRefusalLog refusal_log_;
  RateLimitedLog failure_log_;  // writes not done (an offline servo written cyclically), once a second
};

}  // namespace sms::gateway
