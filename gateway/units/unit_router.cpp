#include "gateway/units/unit_router.h"

#include <algorithm>
#include <stdexcept>

#include <spdlog/spdlog.h>

#include "gateway/service/role_policy.h"
#include "gateway/units/bus_faults.h"
#include "gateway/units/no_jump.h"
#include "gateway/units/passthrough.h"
#include "modbus_map/motion.h"
#include "modbus_map/status_bits.h"
#include "modbus_map/tables.h"
#include "protocol/modbus_pdu.h"
#include "protocol/overloaded.h"

namespace sms::gateway {
namespace {

namespace fc = function_code;
using protocol::function_effect;
using protocol::FunctionEffect;
namespace facts_layout = servo_facts_layout;
using modbus_map::TableId;

// The lowest response level at which a servo answers unicast writes (docs/PROTOCOL.md §2.1 address 8,
// §2.2 address 8, §2.3 address 16). SMSMB servos always answer (Modbus).
struct WriteReplyLevel {
  TableId table;
  std::uint8_t min_level;
};
constexpr WriteReplyLevel kWriteReplyLevels[] = {
    {TableId::Sts, 1},   // 0: only READ and PING answered
    {TableId::Sms1, 1},  // 0: only READ and PING answered
    {TableId::Scs, 1},   // 0: only READ and PING answered
    {TableId::D55d, 2},  // 0 never, 1 READ only, 2 all except broadcast
    {TableId::Smsmb, 0},
};

std::uint16_t saturate16(std::uint64_t value) {
  return static_cast<std::uint16_t>(std::min<std::uint64_t>(value, 0xFFFF));
}

// The answer of a write request, passed on; a write the gateway carried out (answered without
// an exception, or a broadcast finished) feeds the watchdog of its bus first. A refused write
// (read-only, a missing register, a bad value, motion blocked, the bus down) proves nothing of the
// client that sent it, so it must not keep a dead PLC's servo turning.
class FeedOnSuccess final : public Reply::Target {
 public:
  FeedOnSuccess(Reply reply, SafetySupervisor& safety, std::size_t bus)
      : reply_(std::move(reply)), safety_(safety), bus_(bus) {}
  void deliver(std::uint64_t, Bytes response_pdu) override {
    if (response_pdu.empty()) {
      safety_.feed_write(bus_);
      reply_.finish_without_answer();
      return;
    }
    if ((response_pdu[0] & 0x80) == 0) safety_.feed_write(bus_);
    reply_.send(std::move(response_pdu));
  }

 private:
  Reply reply_;
  SafetySupervisor& safety_;
  std::size_t bus_;
};

bool writes(std::uint8_t function) { return function_effect(function) != FunctionEffect::Reads; }

}  // namespace

bool writes_answered(TableId table, std::uint8_t response_level) {
  for (const auto& entry : kWriteReplyLevels) {
    if (entry.table == table) return response_level >= entry.min_level;
  }
  return true;
}

std::array<std::uint16_t, servo_facts_layout::kRegisterCount> servo_fact_registers(const ServoFacts& facts) {
  const std::uint16_t age =
      facts.cache_age ? saturate16(static_cast<std::uint64_t>(std::max<std::int64_t>(facts.cache_age->count(), 0)))
                      : std::uint16_t{0xFFFF};
  return {
      facts.last_status,
      static_cast<std::uint16_t>(facts.online ? 1 : 0),
      age,
      facts.identity,
      static_cast<std::uint16_t>((facts.replies_ok >> 16) & 0xFFFF),
      static_cast<std::uint16_t>(facts.replies_ok & 0xFFFF),
      static_cast<std::uint16_t>((facts.timeouts >> 16) & 0xFFFF),
      static_cast<std::uint16_t>(facts.timeouts & 0xFFFF),
      static_cast<std::uint16_t>(facts.offline_reason),
  };
}

UnitRouter::UnitRouter(const config::Config& config, const UnitCatalog& catalog, std::vector<BusEngine*> engines,
                       PostFn post, SafetySupervisor& safety)
    : gateway_unit_id_(config.modbus_tcp.gateway_unit_id), post_(post), safety_(safety) {
  for (const auto& servo : config.servos) {
    if (servo.bus_index >= engines.size() || engines[servo.bus_index] == nullptr) {
      throw std::invalid_argument("unit " + std::to_string(servo.unit_id) + ": bus '" + servo.bus + "' has no engine");
    }
    BusEngine* engine = engines[servo.bus_index];
    if (servo.passthrough()) {
      passthrough_[servo.unit_id] = std::make_unique<PassthroughUnit>(
          PassthroughUnit{servo.unit_id, engine, servo.servo_id, servo.bus_index, servo.read_only,
                          "unit " + std::to_string(servo.unit_id) + " (bus " + servo.bus + ", slave " +
                              std::to_string(servo.servo_id) + ", passthrough)"});
      continue;
    }
    const CatalogUnit* entry = catalog.servo(servo.unit_id);
    if (entry == nullptr) {
      throw std::invalid_argument("unit " + std::to_string(servo.unit_id) + " is not in the unit catalog");
    }
    const auto& servos = engine->settings().servos;
    const auto settings = std::find_if(servos.begin(), servos.end(),
                                       [&](const ServoSettings& s) { return s.servo_id == servo.servo_id; });
    if (settings == servos.end()) {
      throw std::invalid_argument("unit " + std::to_string(servo.unit_id) + ": servo " +
                                  std::to_string(servo.servo_id) + " is not polled by bus '" + servo.bus + "'");
    }
    const modbus_map::BusRange poll_block{settings->poll_block.address, settings->poll_block.count};
    std::string label = "unit " + std::to_string(servo.unit_id) + " (bus " + servo.bus + ", servo " +
                        std::to_string(servo.servo_id) + ")";
    units_[servo.unit_id] =
        std::make_unique<ServoUnit>(ServoUnit{servo.unit_id, servo.bus_index, engine, servo.servo_id, entry->map,
                                              poll_block, servo.response_level, servo.read_only, std::move(label)});
  }
  gateway_unit_ = std::make_unique<GatewayUnit>(config, catalog, std::move(engines), std::move(post), safety);
}

const ServoUnit* UnitRouter::servo_unit(std::uint8_t unit_id) const { return units_[unit_id].get(); }

UnitRouter::RefusalReason UnitRouter::refusal_reason(const ServoUnit& unit) const {
  if (auto why = safety_.motion_refusal(unit.bus_index, unit.servo_id)) return {"refused: " + *why, true};
  std::string status;
  if (const auto state = unit.engine->cache().state(unit.servo_id); state && state->has_data) {
    status = fmt::format("; last status byte 0x{:02X}", state->counters.last_status);
    const auto faults = modbus_map::status_faults(unit.map.servo_table().id, state->counters.last_status);
    for (std::size_t i = 0; i < faults.size(); ++i) status += (i == 0 ? ": " : ", ") + faults[i];
  }
  return {"the servo refused it or its answers were damaged (no safety rule refuses motion now" + status + ")", false};
}

void UnitRouter::handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) {
  try {
    dispatch(unit_id, pdu, reply);
  } catch (const std::exception& error) {
    // A request the code cannot express on its bus is a bug; answer it instead of taking the
    // io thread (and every other connection) down with it.
    spdlog::error("modbus: unit {}: request {:02X} failed inside the gateway: {}", unit_id, pdu.empty() ? 0 : pdu[0],
                  error.what());
    reply.send(exception_response(pdu.empty() ? 0 : pdu[0], ModbusException::ServerDeviceFailure));
  }
}

void UnitRouter::dispatch(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, const Reply& reply) {
  const std::uint8_t function = pdu.empty() ? 0 : pdu[0];
  const auto fed_on_success = [&](std::size_t bus_index) {
    return Reply(std::make_shared<FeedOnSuccess>(reply, safety_, bus_index), 0, reply.origin_text());
  };
  if (const PassthroughUnit* forwarded = passthrough_[unit_id].get()) {
    forward(*forwarded, pdu, writes(function) ? fed_on_success(forwarded->bus_index) : reply);
    return;
  }
  const ServoUnit* unit = units_[unit_id].get();
  if (unit == nullptr && unit_id != gateway_unit_id_) {
    spdlog::debug("modbus: request for unit {}, which is not configured", unit_id);
    reply.send(exception_response(function, ModbusException::GatewayPathUnavailable));
    return;
  }
  const auto request = parse_request(pdu);
  if (!request) {
    reply.send(exception_response(function, request.error()));
    return;
  }
  if (unit == nullptr) {
    gateway_unit_->handle(*request, reply);
    return;
  }
  handle_servo(*unit, *request, writes(function) ? fed_on_success(unit->bus_index) : reply);
}

void UnitRouter::forward(const PassthroughUnit& unit, std::span<const std::uint8_t> pdu, const Reply& reply) {
  const std::uint8_t function = pdu[0];
  if (refused_as_read_only(unit.read_only, unit.label, function, reply)) return;
  if (!unit.engine->bus_up()) {
    reply.send(exception_response(function, ModbusException::GatewayPathUnavailable));
    return;
  }
  MotionEpoch epoch = 0;
  if (writes(function)) {
    // The gateway cannot tell what a passthrough slave's registers do: every write may move
    // something, so every write is under the safety rules (docs/PLC_GUIDE.md "Safety").
    const auto admitted = admit_motion(unit.bus_index, unit.label, function, reply);
    if (!admitted) return;
    epoch = *admitted;
  }
  forward_pdu(*unit.engine, unit.slave, pdu, post_, reply, unit.label, BroadcastReply::None, epoch);
}

std::optional<MotionEpoch> UnitRouter::admit_motion(std::size_t bus_index, const std::string& what,
                                                    std::uint8_t function, const Reply& reply) {
  return admit_or_refuse(safety_, refusal_log_, bus_index, what, function, reply);
}

bool UnitRouter::refused_as_read_only(bool read_only, const std::string& label, std::uint8_t function,
                                      const Reply& reply) const {
  if (!read_only) return false;
  const auto refusal = read_only_refusal(function);
  if (!refusal) return false;
  spdlog::debug("modbus: {} is read-only in the configuration; FC{:02X} refused", label, function);
  reply.send(exception_response(function, *refusal));
  return true;
}

void UnitRouter::handle_servo(const ServoUnit& unit, const Request& request, const Reply& reply) {
  const std::uint8_t function = function_of(request);
  if (!unit.engine->bus_up()) {
    reply.send(exception_response(function, ModbusException::GatewayPathUnavailable));
    return;
  }
  if (refused_as_read_only(unit.read_only, unit.label, function, reply)) return;
  std::visit(Overloaded{
                 [&](const ReadRegistersRequest& read) {
                   if (read.function == fc::kReadInputRegisters) {
                     read_input(unit, read, reply);
                   } else {
                     read_holding(unit, read.function, read.address, read.count, reply);
                   }
                 },
                 [&](const ReadBitsRequest& read) {
                   if (read.function == fc::kReadCoils) {
                     read_coils(unit, read, reply);
                   } else {
                     read_discrete(unit, read, reply);
                   }
                 },
                 [&](const WriteBitsRequest& write) {
                   auto plan = unit.map.plan_coil_write(write.address, write.values);
                   if (!plan) return refuse(unit, write.function, plan.error(), reply);
                   run_writes(unit, write.function, std::move(*plan), reply,
                              [write](const Reply& r) { r.send(write_response(write)); });
                 },
                 [&](const WriteRegistersRequest& write) {
                   auto plan = unit.map.plan_register_write(write.address, write.values);
                   if (!plan) return refuse(unit, write.function, plan.error(), reply);
                   run_writes(unit, write.function, std::move(*plan), reply,
                              [write](const Reply& r) { r.send(write_response(write)); });
                 },
                 [&](const ReadWriteRegistersRequest& both) {
                   // Both halves are checked before the write goes out: a refused read must not
                   // leave a write behind that the client was told failed.
                   auto write_plan = unit.map.plan_register_write(both.write.address, both.write.values);
                   if (!write_plan) return refuse(unit, both.read.function, write_plan.error(), reply);
                   const auto read_plan = unit.map.plan_holding_read(both.read.address, both.read.count);
                   if (!read_plan) return refuse(unit, both.read.function, read_plan.error(), reply);
                   const std::uint8_t function23 = both.read.function;
                   run_writes(unit, function23, std::move(*write_plan), reply,
                              [this, &unit, function23, read = both.read](const Reply& r) {
                                read_holding(unit, function23, read.address, read.count, r);
                              });
                 },
             },
             request);
}

void UnitRouter::refuse(const ServoUnit& unit, std::uint8_t function, const modbus_map::MapError& error,
                        const Reply& reply) const {
  spdlog::debug("modbus: {} FC{:02X}: {}", unit.label, function, error.message);
  reply.send(exception_response(function, error.code));
}

void UnitRouter::read_holding(const ServoUnit& unit, std::uint8_t function, std::uint16_t start, std::uint16_t count,
                              const Reply& reply) {
  auto plan = unit.map.plan_holding_read(start, count);
  if (!plan) return refuse(unit, function, plan.error(), reply);
  run_reads(unit, function, *plan, reply,
            [this, &unit, function, plan = *plan, reply](std::vector<protocol::Bytes> replies) {
              const auto values = unit.map.registers_from(plan, replies);
              if (!values) return refuse(unit, function, values.error(), reply);
              reply.send(registers_response(function, *values));
            });
}

void UnitRouter::read_input(const ServoUnit& unit, const ReadRegistersRequest& request, const Reply& reply) {
  if (request.address >= facts_layout::kFirstRegister) {
    if (std::uint32_t{request.address} + request.count > facts_layout::kFirstRegister + facts_layout::kRegisterCount) {
      reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
      return;
    }
    const auto registers = servo_fact_registers(facts_of(unit));
    const std::size_t offset = request.address - facts_layout::kFirstRegister;
    reply.send(
        registers_response(request.function, std::span<const std::uint16_t>(registers).subspan(offset, request.count)));
    return;
  }
  const auto plan = unit.map.plan_input_read(request.address, request.count, unit.poll_block);
  if (!plan) return refuse(unit, request.function, plan.error(), reply);
  const auto replies = copy_from_cache(unit, request.function, *plan, reply);
  if (!replies) return;
  const auto values = unit.map.registers_from(*plan, *replies);
  if (!values) return refuse(unit, request.function, values.error(), reply);
  reply.send(registers_response(request.function, *values));
}

void UnitRouter::read_coils(const ServoUnit& unit, const ReadBitsRequest& request, const Reply& reply) {
  auto plan = unit.map.plan_coil_read(request.address, request.count);
  if (!plan) return refuse(unit, request.function, plan.error(), reply);
  run_reads(unit, request.function, *plan, reply,
            [this, &unit, function = request.function, plan = *plan, reply](std::vector<protocol::Bytes> replies) {
              const auto bits = unit.map.bits_from(plan, replies);
              if (!bits) return refuse(unit, function, bits.error(), reply);
              reply.send(bits_response(function, *bits));
            });
}

void UnitRouter::read_discrete(const ServoUnit& unit, const ReadBitsRequest& request, const Reply& reply) {
  if (request.address >= facts_layout::kFirstBit) {
    if (std::uint32_t{request.address} + request.count > facts_layout::kOnlineBit + 1u) {
      reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
      return;
    }
    const ServoFacts facts = facts_of(unit);
    std::vector<bool> bits;
    for (std::uint32_t a = request.address; a < std::uint32_t{request.address} + request.count; ++a) {
      bits.push_back(a == facts_layout::kOnlineBit ? facts.online
                                                   : ((facts.last_status >> (a - facts_layout::kFirstBit)) & 1) != 0);
    }
    reply.send(bits_response(request.function, bits));
    return;
  }
  auto plan = unit.map.plan_discrete_read(request.address, request.count, unit.poll_block);
  if (!plan) return refuse(unit, request.function, plan.error(), reply);
  auto answer = [this, &unit, function = request.function, plan = *plan, reply](std::vector<protocol::Bytes> replies) {
    const auto bits = unit.map.bits_from(plan, replies);
    if (!bits) return refuse(unit, function, bits.error(), reply);
    reply.send(bits_response(function, *bits));
  };
  if (plan->source == modbus_map::ReadSource::PollCache) {
    auto replies = copy_from_cache(unit, request.function, *plan, reply);
    if (replies) answer(std::move(*replies));
  } else {
    run_reads(unit, request.function, *plan, reply, std::move(answer));
  }
}

std::optional<std::vector<protocol::Bytes>> UnitRouter::copy_from_cache(const ServoUnit& unit, std::uint8_t function,
                                                                        const modbus_map::ReadPlan& plan,
                                                                        const Reply& reply) {
  std::vector<protocol::Bytes> replies;
  for (const auto& range : plan.reads) {
    protocol::Bytes bytes(std::size_t{range.count} * unit.map.bytes_per_bus_address());
    switch (unit.engine->cache().copy(unit.servo_id, range.address, bytes)) {
      case CacheRead::Ok: break;
      case CacheRead::NoData:
        // Never answered a poll since the gateway started: nothing to serve, as a live read would fail.
        reply.send(exception_response(function, ModbusException::GatewayTargetFailedToRespond));
        return std::nullopt;
      case CacheRead::UnknownServo:
      case CacheRead::OutsideBlock:
        spdlog::warn("modbus: {}: bus addresses {}+{} are not in the poll cache", unit.label, range.address,
                     range.count);
        reply.send(exception_response(function, ModbusException::IllegalDataAddress));
        return std::nullopt;
    }
    replies.push_back(std::move(bytes));
  }
  return replies;
}

void UnitRouter::run_reads(const ServoUnit& unit, std::uint8_t function, const modbus_map::ReadPlan& plan,
                           const Reply& reply, std::function<void(std::vector<protocol::Bytes>)> then) {
  if (plan.reads.empty()) {  // only gaps: every value is 0, no bus traffic
    then({});
    return;
  }
  auto join = BusJoin::create(plan.reads.size(), post_,
                              [&unit, function, reply, then = std::move(then)](std::vector<BusResult> results) {
                                if (const BusResult* failure = BusJoin::first_failure(results)) {
                                  spdlog::debug("modbus: {} FC{:02X}: {}", unit.label, function, failure->detail);
                                  reply.send(exception_response(function, fault_from(failure->status)));
                                  return;
                                }
                                std::vector<protocol::Bytes> replies;
                                replies.reserve(results.size());
                                for (auto& result : results) replies.push_back(std::move(result.data));
                                then(std::move(replies));
                              });
  for (std::size_t i = 0; i < plan.reads.size(); ++i) {
    const auto& range = plan.reads[i];
    unit.engine->submit(ReadOp{unit.servo_id, range.address, range.count}, Priority::ClientRead, join->completion(i));
  }
}

namespace {

// The frames of one write request, sent one after another: the next only after the servo
// acknowledged the previous one, so a refusal leaves the rest unsent.
struct WriteChain : std::enable_shared_from_this<WriteChain> {
  const ServoUnit* unit = nullptr;
  std::uint8_t function = 0;
  modbus_map::WritePlan plan;
  MotionEpoch epoch = 0;
  std::size_t next = 0;
  Reply reply;
  std::function<void(const Reply&)> after;
  PostFn post;

  WriteChain(const ServoUnit* u, std::uint8_t f, modbus_map::WritePlan p, MotionEpoch e, Reply r,
             std::function<void(const Reply&)> a, PostFn po)
      : unit(u),
        function(f),
        plan(std::move(p)),
        epoch(e),
        reply(std::move(r)),
        after(std::move(a)),
        post(std::move(po)) {}

  void step() {
    if (next == plan.writes.size()) {
      after(reply);
      return;
    }
    const auto& write = plan.writes[next];
    WriteOp op{unit->servo_id, write.address, write.data, plan.staged, expects_write_reply(*unit), epoch};
    unit->engine->submit(
        std::move(op), Priority::ClientWrite, on_io_thread(post, [self = shared_from_this()](BusResult result) {
          if (result.status != BusStatus::Ok) {
            spdlog::debug("modbus: {} FC{:02X}: write failed: {}", self->unit->label, self->function, result.detail);
            self->reply.send(exception_response(self->function, fault_from(result.status)));
            return;
          }
          ++self->next;
          self->step();
        }));
  }
};

}  // namespace

void UnitRouter::run_writes(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan,
                            const Reply& reply, std::function<void(const Reply&)> after) {
  const modbus_map::MotionSpec& spec = modbus_map::motion_spec(unit.map.servo_table().id);
  const modbus_map::ByteOrder order = unit.map.byte_order();
  MotionEpoch epoch = 0;
  // A staged write moves the servo at ACTION; it is refused as a motion write now too, so a
  // latched gateway does not collect moves that a later ACTION would run.
  if (const auto motion = modbus_map::motion_in_plan(spec, order, plan)) {
    const auto admitted = admit_motion(unit.bus_index, unit.label + " (" + *motion + ")", function, reply);
    if (!admitted) return;
    epoch = *admitted;
  }
  if (modbus_map::may_enable_motion(spec, order, plan.writes)) {
    hold_then_enable(unit, function, std::move(plan), epoch, reply, std::move(after));
    return;
  }
  run_admitted_writes(unit, function, std::move(plan), epoch, reply, std::move(after));
}

void UnitRouter::run_admitted_writes(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan,
                                     MotionEpoch epoch, const Reply& reply, std::function<void(const Reply&)> after) {
  auto chain = std::make_shared<WriteChain>(&unit, function, std::move(plan), epoch, reply, std::move(after), post_);
  chain->step();
}

void UnitRouter::hold_then_enable(const ServoUnit& unit, std::uint8_t function, modbus_map::WritePlan plan,
                                  MotionEpoch epoch, const Reply& reply, std::function<void(const Reply&)> after) {
  HoldTarget target{unit.engine,
                    unit.servo_id,
                    &modbus_map::motion_spec(unit.map.servo_table().id),
                    unit.map.byte_order(),
                    expects_write_reply(unit),
                    epoch,
                    unit.label,
                    plan.writes};
  hold_before_enable({std::move(target)}, post_,
                     [this, &unit, function, plan = std::move(plan), epoch, reply,
                      after = std::move(after)](std::optional<BusResult> failure) mutable {
                       if (failure) {
                         // A PLC writing cyclically to an offline servo would otherwise fill the log.
                         failure_log_.warn(fmt::format("modbus: {} FC{:02X}: enabling write not done: {}", unit.label,
                                                       function, failure->detail));
                         reply.send(exception_response(function, fault_from(failure->status)));
                         return;
                       }
                       run_admitted_writes(unit, function, std::move(plan), epoch, reply, std::move(after));
                     });
}

bool answers_writes(TableId table, std::optional<std::uint8_t> configured_level, const BusEngine& engine,
                    std::uint8_t servo_id) {
  if (configured_level) return writes_answered(table, *configured_level);
  const auto state = engine.cache().state(servo_id);
  if (state && state->response_level) return writes_answered(table, *state->response_level);
  return true;  // not read yet: every table's factory level answers writes
}

bool expects_write_reply(const ServoUnit& unit) {
  return answers_writes(unit.map.servo_table().id, unit.configured_response_level, *unit.engine, unit.servo_id);
}

ServoFacts UnitRouter::facts_of(const ServoUnit& unit) const {
  ServoFacts facts;
  const auto state = unit.engine->cache().state(unit.servo_id);
  if (!state) return facts;
  facts.last_status = state->counters.last_status;
  facts.online = state->online;
  facts.offline_reason = state->offline_reason;
  if (const auto age = state->age(SteadyClock::now())) {
    facts.cache_age = std::chrono::duration_cast<std::chrono::milliseconds>(*age);
  }
  facts.identity = state->identity.model.value_or(state->identity.firmware.value_or(0));
  facts.replies_ok = state->counters.replies_ok;
  facts.timeouts = state->counters.timeouts;
  return facts;
}

}  // namespace sms::gateway
