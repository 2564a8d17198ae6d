#include "gateway/units/gateway_unit.h"

#include <algorithm>
#include <array>
#include <limits>
#include <stdexcept>

#include <spdlog/spdlog.h>

#include "gateway/bus/write_batch.h"
#include "gateway/units/bus_faults.h"
#include "gateway/units/no_jump.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"
#include "protocol/overloaded.h"

namespace sms::gateway {
namespace {

namespace fc = function_code;
namespace layout = gateway_unit_layout;

std::uint16_t saturate16(std::uint64_t value) {
  return static_cast<std::uint16_t>(std::min<std::uint64_t>(value, 0xFFFF));
}

// One entry of bus n's block: `words` registers (2 = 32 bits, high word first).
struct BusFactRegister {
  std::uint16_t offset;
  std::uint8_t words;
  std::uint64_t (*value)(const BusFacts&);
};
// docs/PLC_GUIDE.md "The gateway unit", input registers 100 + 20·n ...; 32-bit counters wrap.
constexpr std::array kBusFactRegisters{
    BusFactRegister{0, 1, [](const BusFacts& f) -> std::uint64_t { return f.up ? 1 : 0; }},
    BusFactRegister{1, 1, [](const BusFacts& f) -> std::uint64_t { return saturate16(f.baud / 100); }},
    BusFactRegister{2, 1, [](const BusFacts& f) -> std::uint64_t { return saturate16(f.last_poll_cycle_us); }},
    BusFactRegister{3, 1, [](const BusFacts& f) -> std::uint64_t { return saturate16(f.servos_online); }},
    BusFactRegister{4, 2, [](const BusFacts& f) -> std::uint64_t { return f.frames_ok; }},
    BusFactRegister{6, 2, [](const BusFacts& f) -> std::uint64_t { return f.timeouts; }},
    BusFactRegister{8, 2, [](const BusFacts& f) -> std::uint64_t { return f.checksum_errors; }},
};

void put_words(std::vector<std::uint16_t>& image, std::size_t at, std::uint8_t words, std::uint64_t value) {
  if (words == 2) {
    image[at] = static_cast<std::uint16_t>((value >> 16) & 0xFFFF);
    image[at + 1] = static_cast<std::uint16_t>(value & 0xFFFF);
  } else {
    image[at] = static_cast<std::uint16_t>(value & 0xFFFF);
  }
}

}  // namespace

BusFacts bus_facts(const BusEngine& engine) {
  const BusCountersSnapshot counters = engine.counters();
  BusFacts facts;
  facts.up = engine.bus_up();
  facts.baud = engine.settings().serial.baud;
  facts.last_poll_cycle_us = counters.last_poll_cycle_us;
  facts.servos_online = engine.cache().online_count();
  facts.frames_ok = counters.frames_ok;
  facts.timeouts = counters.timeouts;
  facts.checksum_errors = counters.checksum_errors;
  return facts;
}

GatewayUnit::GatewayUnit(const config::Config& config, const UnitCatalog& catalog, std::vector<BusEngine*> engines,
                         PostFn post, SafetySupervisor& safety, std::chrono::steady_clock::time_point started)
    : engines_(std::move(engines)),
      servo_count_(config.servos.size()),
      post_(std::move(post)),
      safety_(safety),
      started_(started) {
  for (const auto& group_config : config.sync_groups) {
    SyncGroup group;
    group.name = group_config.name;
    group.start = group_config.holding_register_start;
    group.has_move_time = group_config.move_time;
    group.stretch = group_config.stretch;
    group.last_goals.resize(group_config.members.size());
    for (const std::uint8_t unit : group_config.members) {
      const config::ServoConfig* servo = config::find_unit(config, unit);
      const CatalogUnit* entry = catalog.servo(unit);
      if (servo == nullptr || servo->passthrough() || entry == nullptr) {
        throw std::invalid_argument("sync group '" + group_config.name + "': unit " + std::to_string(unit) +
                                    " is not a configured servo with a control table");
      }
      const auto& table = modbus_map::table(*servo->table);
      const modbus_map::FieldSpec* field = modbus_map::field_by_name(table, group_config.field);
      if (field == nullptr || field->access == modbus_map::Access::ReadOnly) {
        throw std::invalid_argument("sync group '" + group_config.name + "': table " + std::string(table.name) +
                                    " of unit " + std::to_string(unit) + " has no writable field '" +
                                    group_config.field + "'");
      }
      if (servo->bus_index >= engines_.size()) {
        throw std::invalid_argument("sync group '" + group_config.name + "': unit " + std::to_string(unit) +
                                    " is on a bus without an engine");
      }
      group.members.push_back(SyncMember{unit, servo->bus_index, servo->servo_id, field, &entry->native_map(),
                                         servo->read_only, servo->response_level});
    }
    groups_.push_back(std::move(group));
  }
}

std::optional<std::vector<std::uint16_t>> GatewayUnit::input_registers(std::uint16_t address,
                                                                       std::uint16_t count) const {
  if (address >= layout::kFirstGroupBlock) {
    const std::vector<std::uint16_t> groups = group_input_registers();
    const std::size_t first = address - layout::kFirstGroupBlock;
    if (first + count > groups.size()) return std::nullopt;
    return std::vector<std::uint16_t>(groups.begin() + static_cast<std::ptrdiff_t>(first),
                                      groups.begin() + static_cast<std::ptrdiff_t>(first + count));
  }
  const std::size_t end = layout::kFirstBusBlock + layout::kBusBlockSize * engines_.size();
  if (std::size_t{address} + count > end) return std::nullopt;

  // The whole image is small (100 + 20 per bus registers); addresses with nothing read as 0.
  std::vector<std::uint16_t> image(end, 0);
  image[layout::kVersion + 0] = SMS_GATEWAY_VERSION_MAJOR;
  image[layout::kVersion + 1] = SMS_GATEWAY_VERSION_MINOR;
  image[layout::kVersion + 2] = SMS_GATEWAY_VERSION_PATCH;
  const auto uptime = std::chrono::duration_cast<std::chrono::seconds>(std::chrono::steady_clock::now() - started_);
  put_words(image, layout::kUptime, 2, static_cast<std::uint64_t>(uptime.count()));
  image[layout::kBusCount] = saturate16(engines_.size());
  image[layout::kServoCount] = saturate16(servo_count_);
  const SafetyFacts safety = safety_.facts();
  image[layout::kEStopLatched] = safety.estop_latched ? 1 : 0;
  put_words(image, layout::kEStopCount, 2, safety.estops);
  std::uint64_t owed = 0, failed = 0;
  for (const auto& bus : safety.buses) {
    owed += bus.owed_stops;
    failed += bus.failed_stops;
  }
  image[layout::kOwedStops] = saturate16(owed);
  put_words(image, layout::kFailedStops, 2, failed);
  std::size_t late = 0;
  for (const BusEngine* engine : engines_) late += engine->cache().offline_count(OfflineReason::AnswersLate);
  image[layout::kLateServos] = saturate16(late);
  for (std::size_t bus = 0; bus < engines_.size(); ++bus) {
    const std::size_t block = layout::kFirstBusBlock + layout::kBusBlockSize * bus;
    // Only the blocks the request touches are worth the counters' atomics.
    if (block >= std::size_t{address} + count || block + layout::kBusBlockSize <= address) continue;
    const BusFacts facts = bus_facts(*engines_[bus]);
    for (const auto& entry : kBusFactRegisters) put_words(image, block + entry.offset, entry.words, entry.value(facts));
    if (bus < safety.buses.size()) {
      const BusSafetyFacts& watchdog = safety.buses[bus];
      const std::size_t at = block + layout::kWatchdogState;
      image[at] = static_cast<std::uint16_t>(watchdog.state);
      image[at + 1] =
          watchdog.since_feed
              ? saturate16(static_cast<std::uint64_t>(std::max<std::int64_t>(watchdog.since_feed->count(), 0)))
              : std::uint16_t{0xFFFF};
      put_words(image, at + 2, 2, watchdog.trips);
      image[at + 4] = saturate16(static_cast<std::uint64_t>(watchdog.timeout.count()));
      image[at + 5] = static_cast<std::uint16_t>(watchdog.last_cause);
      put_words(image, at + 6, 2,
                watchdog.last_stop_latency ? static_cast<std::uint64_t>(watchdog.last_stop_latency->count()) : 0);
      image[at + 8] = watchdog.motion_blocked ? 1 : 0;
      image[at + 9] = saturate16(watchdog.owed_stops);
    }
  }
  return std::vector<std::uint16_t>(image.begin() + address, image.begin() + address + count);
}

void GatewayUnit::handle(const Request& request, const Reply& reply) {
  std::visit(Overloaded{
                 [&](const ReadRegistersRequest& read) {
                   if (read.function == fc::kReadInputRegisters) {
                     const auto values = input_registers(read.address, read.count);
                     reply.send(values ? registers_response(read.function, *values)
                                       : exception_response(read.function, ModbusException::IllegalDataAddress));
                   } else if (heartbeat_range(read.address, read.count)) {
                     read_heartbeats(read.function, read.address, read.count, reply);
                   } else {
                     read_sync_registers(read.function, read.address, read.count, reply);
                   }
                 },
                 [&](const ReadBitsRequest& read) {
                   const bool coils_read = read.function == fc::kReadCoils;
                   const std::uint32_t end = std::uint32_t{read.address} + read.count;
                   if (end > (coils_read ? layout::kCoilCount : layout::kDiscreteInputCount)) {
                     reply.send(exception_response(read.function, ModbusException::IllegalDataAddress));
                     return;
                   }
                   std::vector<bool> bits;
                   if (coils_read) {
                     bits = coils();
                   } else {
                     const SafetyFacts facts = safety_.facts();
                     // All from one snapshot: the bits never disagree with each other.
                     const auto any = [&](auto predicate) {
                       return std::any_of(facts.buses.begin(), facts.buses.end(), predicate);
                     };
                     bits = {facts.estop_latched,
                             any([](const BusSafetyFacts& b) { return b.state == WatchdogState::Tripped; }),
                             any([](const BusSafetyFacts& b) { return b.motion_blocked; }),
                             any([](const BusSafetyFacts& b) { return b.owed_stops > 0; }), facts.state_not_persisted};
                   }
                   reply.send(bits_response(read.function,
                                            std::vector<bool>(bits.begin() + read.address, bits.begin() + end)));
                 },
                 [&](const WriteBitsRequest& write) { write_coil(write, reply); },
                 [&](const WriteRegistersRequest& write) {
                   auto answer = [write](const Reply& r) { r.send(write_response(write)); };
                   if (heartbeat_range(write.address, static_cast<std::uint16_t>(write.values.size()))) {
                     write_heartbeats(write);
                     reply.send(write_response(write));
                     return;
                   }
                   write_sync_registers(write, reply, answer);
                 },
                 [&](const ReadWriteRegistersRequest& both) {
                   if (heartbeat_range(both.write.address, static_cast<std::uint16_t>(both.write.values.size()))) {
                     write_heartbeats(both.write);
                     if (heartbeat_range(both.read.address, both.read.count)) {
                       read_heartbeats(both.read.function, both.read.address, both.read.count, reply);
                     } else {
                       read_sync_registers(both.read.function, both.read.address, both.read.count, reply);
                     }
                     return;
                   }
                   write_sync_registers(both.write, reply, [this, read = both.read](const Reply& r) {
                     if (heartbeat_range(read.address, read.count)) {
                       read_heartbeats(read.function, read.address, read.count, r);
                     } else {
                       read_sync_registers(read.function, read.address, read.count, r);
                     }
                   });
                 },
             },
             request);
}

const GatewayUnit::SyncMember* GatewayUnit::sync_member_at(std::uint16_t address) const {
  for (const auto& group : groups_) {
    if (address >= group.start && address < group.start + group.members.size()) {
      return &group.members[address - group.start];
    }
  }
  return nullptr;
}

void GatewayUnit::read_sync_registers(std::uint8_t function, std::uint16_t address, std::uint16_t count,
                                      const Reply& reply) {
  // Registers in order: a member's live value, or a move time (held by the gateway).
  std::vector<std::uint16_t> values(count, 0);
  std::vector<const SyncMember*> members;
  std::vector<std::size_t> at;  // where each member's value goes
  for (std::uint32_t a = address; a < std::uint32_t{address} + count; ++a) {
    const SyncMember* member = sync_member_at(static_cast<std::uint16_t>(a));
    if (member == nullptr) {
      if (const SyncGroup* group = move_time_group_at(static_cast<std::uint16_t>(a))) {
        values[a - address] = group->move_time_ms;
        continue;
      }
      reply.send(exception_response(function, ModbusException::IllegalDataAddress));
      return;
    }
    members.push_back(member);
    at.push_back(a - address);
  }
  if (members.empty()) {
    reply.send(registers_response(function, values));
    return;
  }
  // Each member's value is read and converted by its own native register map.
  std::vector<modbus_map::ReadPlan> plans;
  for (const SyncMember* member : members) {
    auto plan = member->map->plan_holding_read(member->field->addr, 1);
    if (!plan || plan->reads.size() != 1) {
      reply.send(exception_response(function, ModbusException::IllegalDataAddress));
      return;
    }
    plans.push_back(std::move(*plan));
  }
  auto join = BusJoin::create(members.size(), post_,
                              [function, members, plans, at, values, reply](std::vector<BusResult> results) mutable {
                                if (const BusResult* failure = BusJoin::first_failure(results)) {
                                  reply.send(exception_response(function, fault_from(failure->status)));
                                  return;
                                }
                                for (std::size_t i = 0; i < members.size(); ++i) {
                                  const protocol::Bytes replies[] = {results[i].data};
                                  const auto value = members[i]->map->registers_from(plans[i], replies);
                                  if (!value) {
                                    reply.send(exception_response(function, value.error().code));
                                    return;
                                  }
                                  values[at[i]] = value->at(0);
                                }
                                reply.send(registers_response(function, values));
                              });
  for (std::size_t i = 0; i < members.size(); ++i) {
    const auto& range = plans[i].reads.front();
    engines_[members[i]->bus]->submit(ReadOp{members[i]->servo_id, range.address, range.count}, Priority::ClientRead,
                                      join->completion(i));
  }
}

GatewayUnit::SyncGroup* GatewayUnit::group_of(const SyncMember* member) {
  for (auto& group : groups_) {
    if (!group.members.empty() && member >= group.members.data() &&
        member < group.members.data() + group.members.size()) {
      return &group;
    }
  }
  return nullptr;
}

GatewayUnit::SyncGroup* GatewayUnit::move_time_group_at(std::uint16_t address) {
  for (auto& group : groups_) {
    if (group.has_move_time && address == group.start + group.members.size()) return &group;
  }
  return nullptr;
}

void GatewayUnit::write_sync_registers(const WriteRegistersRequest& request, const Reply& reply,
                                       std::function<void(const Reply&)> after) {
  // Validate everything before the first frame: a refused write changes nothing.
  // Packet buses: one SYNC WRITE per bus (per field address, should tables differ); modbus-rtu
  // has no SYNC WRITE, so its members get one acknowledged write each.
  std::vector<MemberWrite> writes;
  std::vector<std::pair<SyncGroup*, std::uint16_t>> move_times;  // move time registers written
  for (std::size_t i = 0; i < request.values.size(); ++i) {
    const auto address = static_cast<std::uint16_t>(request.address + i);
    const SyncMember* member = sync_member_at(address);
    if (member == nullptr) {
      if (SyncGroup* group = move_time_group_at(address)) {
        move_times.emplace_back(group, request.values[i]);
        continue;
      }
    }
    if (member == nullptr || member->read_only) {
      reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
      return;
    }
    const SyncGroup* group = group_of(member);
    writes.push_back(MemberWrite{member, static_cast<std::size_t>(member - group->members.data()), request.values[i]});
  }
  // Like every write, it feeds the watchdogs of the buses it is for once it is carried out.
  std::vector<std::size_t> buses;
  const auto note_bus = [&buses](std::size_t bus) {
    if (std::find(buses.begin(), buses.end(), bus) == buses.end()) buses.push_back(bus);
  };
  for (const MemberWrite& write : writes) note_bus(write.member->bus);
  for (const auto& [group, value] : move_times) {
    for (const SyncMember& member : group->members) note_bus(member.bus);
  }
  const auto store_move_times = [move_times] {
    for (const auto& [group, value] : move_times) group->move_time_ms = value;
  };
  if (writes.empty()) {  // only move times: kept for the next goals; a write carried out all the same
    store_move_times();
    for (const std::size_t bus : buses) safety_.feed_write(bus);
    after(reply);
    return;
  }
  // Goals with a move time (written now or before) are a timed move: every axis arrives together.
  SyncGroup& first_group = *group_of(writes.front().member);
  std::uint16_t move_time_ms = first_group.move_time_ms;
  for (const auto& [group, value] : move_times) {
    if (group == &first_group) move_time_ms = value;
  }
  if (first_group.has_move_time && move_time_ms != 0) {
    const bool one_group = std::all_of(
        writes.begin(), writes.end(), [&](const MemberWrite& write) { return group_of(write.member) == &first_group; });
    if (!one_group) {
      spdlog::debug("gateway unit: sync group '{}': a timed move writes the goals of one group only", first_group.name);
      reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
      return;
    }
    timed_move(first_group, std::move(writes), move_time_ms, request, reply,
               [store_move_times, after = std::move(after)](const Reply& r) {
                 store_move_times();
                 after(r);
               });
    return;
  }

  std::vector<WriteBatch> batches;  // per bus: one SYNC WRITE per field on packet buses
  for (const BusEngine* engine : engines_) {
    batches.emplace_back(engine->settings().protocol != protocol::BusProtocol::ModbusRtu);
  }
  for (const MemberWrite& write : writes) {
    const SyncMember* member = write.member;
    auto bytes = member->map->field_bytes(*member->field, write.value);
    if (!bytes) {
      spdlog::debug("gateway unit: sync group '{}' unit {}: {}", group_of(member)->name, member->unit_id,
                    bytes.error().message);
      reply.send(exception_response(request.function, bytes.error().code));
      return;
    }
    batches[member->bus].add(member->servo_id, member->field->addr, std::move(*bytes));
  }
  std::vector<Frame> frames;
  for (std::size_t bus = 0; bus < batches.size(); ++bus) {
    for (BusOp& op : batches[bus].frames()) frames.push_back(Frame{bus, std::move(op)});
  }
  // A motion field needs admission on every bus the write reaches.
  std::vector<MotionEpoch> epochs(engines_.size(), 0);
  std::vector<const SyncMember*> motion_member(engines_.size(), nullptr);
  for (const MemberWrite& write : writes) {
    const SyncMember* member = write.member;
    if (modbus_map::is_motion_field(modbus_map::motion_spec(member->map->servo_table().id), member->field->name)) {
      motion_member[member->bus] = member;
    }
  }
  for (std::size_t bus = 0; bus < engines_.size(); ++bus) {
    if (motion_member[bus] == nullptr) continue;
    const auto admitted = admit_or_refuse(
        safety_, refusal_log_, bus, "gateway unit sync group (" + std::string(motion_member[bus]->field->name) + ")",
        request.function, reply);
    if (!admitted) return;
    epochs[bus] = *admitted;
  }
  for (Frame& frame : frames) {
    std::visit(
        [&](auto& op) {
          if constexpr (requires { op.motion_epoch; }) op.motion_epoch = epochs[frame.bus];
        },
        frame.op);
  }
  // A member the write may enable (torque on, d55d wake or brake release, a drive change) gets the
  // hold of its goal block first where it needs one ("no jump on enable", no_jump.h).
  std::vector<HoldTarget> switched_on;
  for (const MemberWrite& write : writes) {
    const SyncMember* member = write.member;
    const auto& spec = modbus_map::motion_spec(member->map->servo_table().id);
    auto bytes = member->map->field_bytes(*member->field, write.value);
    if (!bytes) continue;  // checked above
    std::vector<modbus_map::BusWrite> bus_writes{{member->field->addr, std::move(*bytes)}};
    if (!modbus_map::may_enable_motion(spec, member->map->byte_order(), bus_writes)) continue;
    switched_on.push_back(HoldTarget{
        engines_[member->bus], member->servo_id, &spec, member->map->byte_order(),
        answers_writes(member->map->servo_table().id, member->response_level, *engines_[member->bus], member->servo_id),
        epochs[member->bus], "unit " + std::to_string(member->unit_id), std::move(bus_writes)});
  }
  // Goals written at each axis's own speed: the group's timed-move registers show no move.
  send_frames(std::move(frames), std::move(switched_on), std::move(buses), request.function, reply,
              [this, writes, store_move_times, after = std::move(after)](const Reply& r) {
                store_move_times();
                for (const MemberWrite& write : writes) {
                  SyncGroup& group = *group_of(write.member);
                  if (!group.has_move_time) continue;
                  record_goal(group, write);
                  group.timed.ends.reset();
                }
                after(r);
              });
}

void GatewayUnit::send_frames(std::vector<Frame> frames, std::vector<HoldTarget> switched_on,
                              std::vector<std::size_t> buses, std::uint8_t function, const Reply& reply,
                              std::function<void(const Reply&)> after, const std::function<void()>& failed) {
  auto send = [this, frames = std::move(frames), buses = std::move(buses), function, reply, after = std::move(after),
               failed](std::optional<BusResult> hold_failure) mutable {
    if (hold_failure) {
      failure_log_.warn("gateway unit: sync group enabling write not done: " + hold_failure->detail);
      if (failed) failed();
      reply.send(exception_response(function, fault_from(hold_failure->status)));
      return;
    }
    auto join = BusJoin::create(
        frames.size(), post_,
        [this, buses, function, reply, after = std::move(after), failed](const std::vector<BusResult>& results) {
          if (const BusResult* failure = BusJoin::first_failure(results)) {
            failure_log_.warn("gateway unit: sync group write failed: " + failure->detail);
            if (failed) failed();
            reply.send(exception_response(function, fault_from(failure->status)));
            return;
          }
          for (const std::size_t bus : buses) safety_.feed_write(bus);
          after(reply);
        });
    for (std::size_t i = 0; i < frames.size(); ++i) {
      engines_[frames[i].bus]->submit(std::move(frames[i].op), Priority::ClientWrite, join->completion(i));
    }
  };
  if (switched_on.empty()) {
    send(std::nullopt);
    return;
  }
  hold_before_enable(std::move(switched_on), post_, std::move(send));
}

std::vector<bool> GatewayUnit::coils() const {
  // Coil 0 reads 0: ACTION is an event, not a state.
  return {false, safety_.estop_latched(), safety_.any_tripped()};
}

bool GatewayUnit::heartbeat_range(std::uint16_t address, std::uint16_t count) const {
  return address >= config::kHeartbeatRegisterBase && count >= 1 &&
         std::size_t{address} + count <= config::kHeartbeatRegisterBase + engines_.size();
}

void GatewayUnit::read_heartbeats(std::uint8_t function, std::uint16_t address, std::uint16_t count,
                                  const Reply& reply) const {
  std::vector<std::uint16_t> values;
  for (std::uint16_t i = 0; i < count; ++i) {
    values.push_back(safety_.heartbeat_value(address - config::kHeartbeatRegisterBase + i).value_or(0));
  }
  reply.send(registers_response(function, values));
}

void GatewayUnit::write_heartbeats(const WriteRegistersRequest& request) {
  for (std::size_t i = 0; i < request.values.size(); ++i) {
    safety_.feed_heartbeat(request.address - config::kHeartbeatRegisterBase + i, request.values[i]);
  }
}

void GatewayUnit::write_coil(const WriteBitsRequest& request, const Reply& reply) {
  if (request.values.size() != 1) {  // each coil is a command of its own: one per request
    reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
    return;
  }
  switch (request.address) {
    case layout::kActionCoil: write_action_coil(request, reply); return;
    case layout::kEStopCoil: write_estop_coil(request, reply); return;
    case layout::kWatchdogCoil:
      if (request.values[0]) {  // a trip comes from silence, not from a write
        reply.send(exception_response(request.function, ModbusException::IllegalDataValue));
        return;
      }
      safety_.rearm_watchdogs(reply.origin());
      reply.send(write_response(request));
      return;
    default: reply.send(exception_response(request.function, ModbusException::IllegalDataAddress));
  }
}

void GatewayUnit::write_estop_coil(const WriteBitsRequest& request, const Reply& reply) {
  if (!request.values[0]) {
    safety_.reset_estop(reply.origin());
    reply.send(write_response(request));
    return;
  }
  // Answered once every bus has its stop frames on the wire; the latch holds either way.
  safety_.estop(
      post_,
      [request, reply](bool ok) {
        if (!ok) {
          spdlog::error("gateway unit: e-stop latched, but a bus could not take its stop frames (see above)");
          reply.send(exception_response(request.function, ModbusException::ServerDeviceFailure));
          return;
        }
        reply.send(write_response(request));
      },
      reply.origin());
}

void GatewayUnit::write_action_coil(const WriteBitsRequest& request, const Reply& reply) {
  // Staged writes exist on packet buses only: ACTION goes to those.
  std::vector<BusEngine*> packet_buses;
  for (BusEngine* engine : engines_) {
    if (engine->settings().protocol != protocol::BusProtocol::ModbusRtu) packet_buses.push_back(engine);
  }
  if (!request.values[0] || packet_buses.empty()) {  // writing 0 asks for nothing
    reply.send(write_response(request));
    return;
  }
  // ACTION runs staged moves: a motion write on every bus it goes to.
  std::vector<MotionEpoch> epochs;
  for (std::size_t bus = 0; bus < engines_.size(); ++bus) {
    if (engines_[bus]->settings().protocol == protocol::BusProtocol::ModbusRtu) continue;
    const auto admitted =
        admit_or_refuse(safety_, refusal_log_, bus, "gateway unit ACTION (coil 0)", request.function, reply);
    if (!admitted) return;
    epochs.push_back(*admitted);
  }
  auto join =
      BusJoin::create(packet_buses.size(), post_, [this, request, reply](const std::vector<BusResult>& results) {
        if (const BusResult* failure = BusJoin::first_failure(results)) {
          spdlog::warn("gateway unit: ACTION failed on a bus: {}", failure->detail);
          reply.send(exception_response(request.function, fault_from(failure->status)));
          return;
        }
        for (std::size_t bus = 0; bus < engines_.size(); ++bus) {
          if (engines_[bus]->settings().protocol != protocol::BusProtocol::ModbusRtu) safety_.feed_write(bus);
        }
        reply.send(write_response(request));
      });
  for (std::size_t i = 0; i < packet_buses.size(); ++i) {
    packet_buses[i]->submit(ActionOp{epochs[i]}, Priority::ClientWrite, join->completion(i));
  }
}

}  // namespace sms::gateway
