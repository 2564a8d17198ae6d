// The gateway unit's timed group moves (docs/PLC_GUIDE.md "Timed group moves"): goals and a move
// time in; each axis's present position from the poll cache (or read when the cache missed a
// poll); per axis the speed and acceleration counts whose trapezoid takes the move time
// (modbus_map/timed_move.h); out one SYNC WRITE per bus of acceleration, goal and speed, or on a
// modbus-rtu bus one write per servo in unit order. The same admission as every motion write.
#include <algorithm>
#include <cmath>
#include <optional>
#include <span>
#include <string_view>

#include <spdlog/spdlog.h>

#include "gateway/bus/write_batch.h"
#include "gateway/units/bus_faults.h"
#include "gateway/units/gateway_unit.h"
#include "gateway/units/unit_router.h"
#include "modbus_map/motion.h"
#include "modbus_map/tables.h"
#include "modbus_map/timed_move.h"

namespace sms::gateway {
namespace {

namespace layout = gateway_unit_layout;
using modbus_map::FieldSpec;

// How far from the time asked an accepted timed move may arrive (docs/PLC_GUIDE.md "Timed group moves").
constexpr double kMoveTimeTolerance = 0.05;
using modbus_map::RegisterMap;

// SMSMB registers travel high byte first whatever the map's byte order.
modbus_map::ByteOrder wire_order(const RegisterMap& map) {
  return map.servo_table().addressing == modbus_map::Addressing::Register ? modbus_map::ByteOrder::HighFirst
                                                                          : map.byte_order();
}

std::int32_t field_value(const FieldSpec& field, const RegisterMap& map, std::span<const std::uint8_t> bytes) {
  return modbus_map::decode_value(field, modbus_map::load_raw(bytes, field.size, wire_order(map)));
}

// Bytes of one field as the cache and a READ hold them.
std::size_t wire_bytes(const RegisterMap& map, const FieldSpec& field) {
  const auto addressing = map.servo_table().addressing;
  return std::size_t{modbus_map::address_span(addressing, field)} * modbus_map::bytes_per_address(addressing);
}

const FieldSpec& present_position_field(const RegisterMap& map) {
  const auto& table = map.servo_table();
  return *modbus_map::field_by_name(table, modbus_map::motion_spec(table.id).present_position);
}

// How old a cached present position may be: one poll period after the cycle that read it, so
// one poll period plus that cycle's length (the block is read somewhere inside its cycle, and a
// cache refreshed on time is up to that old). Older, the servo missed a poll: read it live.
std::chrono::steady_clock::duration fresh_age(const BusEngine& engine) {
  const std::chrono::steady_clock::duration cycle = std::chrono::microseconds(engine.counters().last_poll_cycle_us);
  return std::max<std::chrono::steady_clock::duration>(engine.settings().poll_period, cycle) + cycle;
}

std::chrono::milliseconds whole_ms_up(double seconds) {
  return std::chrono::milliseconds(static_cast<std::int64_t>(std::ceil(seconds * 1000.0 - 1e-9)));
}

std::uint16_t saturate16(std::int64_t value) {
  return static_cast<std::uint16_t>(std::clamp<std::int64_t>(value, 0, 0xFFFF));
}

// The bus range to read before a timed move: from the first angle limit to the last of the
// limits and the resolution field (d55d, whose units follow it), so one READ tells whether the
// goal is inside the axis's limits, whether the servo is in wheel or PWM mode, and its units.
modbus_map::BusRange servo_context(const RegisterMap& map, const modbus_map::TimedMoveSpec& spec) {
  const auto& table = map.servo_table();
  const auto& motion = modbus_map::motion_spec(table.id);
  std::uint16_t first = 0xFFFF;
  std::uint16_t end = 0;
  for (const std::string_view name : {motion.min_limit, motion.max_limit, spec.resolution}) {
    const FieldSpec* field = name.empty() ? nullptr : modbus_map::field_by_name(table, name);
    if (field == nullptr) continue;
    first = std::min(first, field->addr);
    end = std::max<std::uint16_t>(end, field->addr + modbus_map::address_span(table.addressing, *field));
  }
  return modbus_map::BusRange{first, static_cast<std::uint16_t>(end - first)};
}

// `spec` at the servo's resolution read in `bytes` (from bus address `first`), or why the axis
// cannot take the move to `goal`: both angle limits 0 on a table without a mode field (d55d
// wheel mode: goals are relative; scs PWM), or a goal outside its angle limits (the axis would
// stop at the limit and never arrive).
Expected<modbus_map::TimedMoveSpec> spec_from_context(const RegisterMap& map, const modbus_map::TimedMoveSpec& spec,
                                                      std::uint16_t first, std::span<const std::uint8_t> bytes,
                                                      std::int32_t goal) {
  const auto& table = map.servo_table();
  const auto value_of = [&](std::string_view name) -> std::optional<std::int32_t> {
    const FieldSpec* field = name.empty() ? nullptr : modbus_map::field_by_name(table, name);
    if (field == nullptr) return std::nullopt;
    const std::size_t at = std::size_t{static_cast<std::uint16_t>(field->addr - first)} * map.bytes_per_bus_address();
    return field_value(*field, map, bytes.subspan(at, wire_bytes(map, *field)));
  };
  const auto& motion = modbus_map::motion_spec(table.id);
  const auto min = value_of(motion.min_limit);
  const auto max = value_of(motion.max_limit);
  if (min && max && *min == 0 && *max == 0) {
    if (motion.mode.empty()) {
      return unexpected(std::string("both angle limits are 0 (") +
                        (motion.modes.empty() ? "wheel mode: relative goals" : "PWM mode") +
                        "); a timed move needs position mode");
    }
  } else if (min && max && (goal < *min || goal > *max)) {
    return unexpected("goal " + std::to_string(goal) + " is outside its angle limits " + std::to_string(*min) + ".." +
                      std::to_string(*max) + ": it would stop at the limit and never arrive");
  }
  return modbus_map::at_resolution(spec, value_of(spec.resolution).value_or(spec.reference_resolution));
}

// One member's writes merged where they touch: sts acceleration, goal, time and speed are one
// block of 7 bytes from 41; SMSMB's torque switch sits between goal and acceleration, so two.
struct Block {
  std::uint16_t address;
  std::uint16_t end;  // address after the block
  protocol::Bytes bytes;
};

std::vector<Block> merged(std::vector<Block> writes) {
  std::sort(writes.begin(), writes.end(), [](const Block& a, const Block& b) { return a.address < b.address; });
  std::vector<Block> blocks;
  for (Block& write : writes) {
    if (!blocks.empty() && blocks.back().end == write.address) {
      blocks.back().bytes.insert(blocks.back().bytes.end(), write.bytes.begin(), write.bytes.end());
      blocks.back().end = write.end;
    } else {
      blocks.push_back(std::move(write));
    }
  }
  return blocks;
}

}  // namespace

void GatewayUnit::record_goal(SyncGroup& group, const MemberWrite& write) const {
  const SyncMember& member = *write.member;
  if (auto bytes = member.map->field_bytes(*member.field, write.value)) {
    group.last_goals[write.index] = field_value(*member.field, *member.map, *bytes);
  }
}

std::vector<std::uint16_t> GatewayUnit::group_input_registers() const {
  std::vector<std::uint16_t> image(layout::kGroupBlockSize * groups_.size(), 0);
  const auto now = std::chrono::steady_clock::now();
  const SafetyFacts facts = safety_.facts();
  const auto put = [&](std::size_t g, layout::GroupRegister which, std::uint16_t value) {
    image[g * layout::kGroupBlockSize + static_cast<std::uint16_t>(which)] = value;
  };
  for (std::size_t g = 0; g < groups_.size(); ++g) {
    const SyncGroup& group = groups_[g];
    // A stop (e-stop, watchdog) ends the move: nothing is running toward the plan any more.
    const bool stopped = std::any_of(group.members.begin(), group.members.end(), [&](const SyncMember& member) {
      return member.bus < facts.buses.size() && facts.buses[member.bus].motion_blocked;
    });
    std::int64_t to_go = 0;
    for (std::size_t i = 0; i < group.members.size(); ++i) {
      if (!group.last_goals[i]) continue;
      const SyncMember& member = group.members[i];
      const FieldSpec& present = present_position_field(*member.map);
      protocol::Bytes bytes(wire_bytes(*member.map, present));
      if (engines_[member.bus]->cache().copy(member.servo_id, present.addr, bytes) != CacheRead::Ok) continue;
      to_go = std::max<std::int64_t>(to_go, std::abs(*group.last_goals[i] - field_value(present, *member.map, bytes)));
    }
    // Moving and time left follow the axes as the poll cache sees them, not only the plan: a move
    // whose axes are all there (or that moved none) is over, whatever time the plan had left.
    std::int64_t left_ms = 0;
    if (group.timed.ends && !stopped && *group.timed.ends > now && to_go > 0) {
      left_ms = std::chrono::duration_cast<std::chrono::milliseconds>(*group.timed.ends - now).count() + 1;
    }
    put(g, layout::GroupRegister::Moving, left_ms > 0 ? 1 : 0);
    put(g, layout::GroupRegister::TimeLeft, saturate16(left_ms));
    put(g, layout::GroupRegister::DistanceToGo, saturate16(to_go));
    put(g, layout::GroupRegister::LastMove, static_cast<std::uint16_t>(group.timed.result));
    put(g, layout::GroupRegister::LimitingUnit, group.timed.limiting_unit);
    put(g, layout::GroupRegister::ShortestTime, saturate16(group.timed.shortest.count()));
    put(g, layout::GroupRegister::MoveTime, saturate16(group.timed.used.count()));
  }
  return image;
}

void GatewayUnit::refuse_timed_move(SyncGroup& group) {
  group.timed.result = layout::TimedMoveResult::Refused;
  group.timed.used = std::chrono::milliseconds(0);
}

void GatewayUnit::timed_move(SyncGroup& group, std::vector<MemberWrite> writes, std::uint16_t move_time_ms,
                             const WriteRegistersRequest& request, const Reply& reply,
                             std::function<void(const Reply&)> after) {
  for (const MemberWrite& write : writes) {
    const SyncMember& member = *write.member;
    if (auto bytes = member.map->field_bytes(*member.field, write.value); !bytes) {
      spdlog::debug("gateway unit: sync group '{}' unit {}: {}", group.name, member.unit_id, bytes.error().message);
      refuse_timed_move(group);
      reply.send(exception_response(request.function, bytes.error().code));
      return;
    }
  }
  // Each axis's table profile; a table whose units follow a resolution field (d55d) gets its
  // servo's, read with the fields that choose its drive.
  std::vector<modbus_map::TimedMoveSpec> specs;
  for (const MemberWrite& write : writes) {
    const auto* spec = modbus_map::timed_move_spec(write.member->map->servo_table().id);
    if (spec == nullptr) {  // no such table today; kept so a new table cannot slip through
      spdlog::warn("gateway unit: sync group '{}' unit {}: table {} cannot take a timed move", group.name,
                   write.member->unit_id, write.member->map->servo_table().name);
      refuse_timed_move(group);
      reply.send(exception_response(request.function, ModbusException::IllegalDataValue));
      return;
    }
    specs.push_back(*spec);
  }
  // Reads before the plan: present positions the poll cache does not have fresh (fresh_age),
  // and each axis's angle limits (and d55d's resolution).
  struct Read {
    std::size_t axis;
    bool context;  // the resolution and angle limits, else the present position
    ReadOp op;
  };
  std::vector<Read> reads;
  const auto now = std::chrono::steady_clock::now();
  std::vector<std::int32_t> present(writes.size(), 0);
  for (std::size_t i = 0; i < writes.size(); ++i) {
    const SyncMember& member = *writes[i].member;
    const FieldSpec& field = present_position_field(*member.map);
    const BusEngine& engine = *engines_[member.bus];
    protocol::Bytes bytes(wire_bytes(*member.map, field));
    CachedServoState state;
    const auto age = engine.cache().copy(member.servo_id, field.addr, bytes, &state) == CacheRead::Ok ? state.age(now)
                                                                                                      : std::nullopt;
    if (age && *age <= fresh_age(engine)) {
      present[i] = field_value(field, *member.map, bytes);
    } else {
      reads.push_back(Read{
          i, false,
          ReadOp{member.servo_id, field.addr, modbus_map::address_span(member.map->servo_table().addressing, field)}});
    }
    const auto range = servo_context(*member.map, specs[i]);
    reads.push_back(Read{i, true, ReadOp{member.servo_id, range.address, range.count}});
  }
  SyncGroup* const target = &group;
  const std::uint8_t function = request.function;
  auto join = BusJoin::create(
      reads.size(), post_,
      [this, target, writes, specs, present, reads, move_time_ms, function, reply,
       after = std::move(after)](const std::vector<BusResult>& results) mutable {
        if (const BusResult* failure = BusJoin::first_failure(results)) {
          spdlog::warn("gateway unit: sync group '{}': a servo was not read, no move: {}", target->name,
                       failure->detail);
          refuse_timed_move(*target);
          reply.send(exception_response(function, fault_from(failure->status)));
          return;
        }
        for (std::size_t k = 0; k < reads.size(); ++k) {
          const SyncMember& member = *writes[reads[k].axis].member;
          if (results[k].data.size() != std::size_t{reads[k].op.count} * member.map->bytes_per_bus_address()) {
            spdlog::warn("gateway unit: sync group '{}' unit {}: a read answered {} bytes", target->name,
                         member.unit_id, results[k].data.size());
            refuse_timed_move(*target);
            reply.send(exception_response(function, ModbusException::ServerDeviceFailure));
            return;
          }
          if (!reads[k].context) {
            present[reads[k].axis] = field_value(present_position_field(*member.map), *member.map, results[k].data);
            continue;
          }
          const MemberWrite& write = writes[reads[k].axis];
          const auto goal =
              field_value(*member.field, *member.map, *member.map->field_bytes(*member.field, write.value));
          const auto scaled =
              spec_from_context(*member.map, specs[reads[k].axis], reads[k].op.address, results[k].data, goal);
          if (!scaled) {
            spdlog::info("gateway unit: sync group '{}' unit {}: {}; nothing written", target->name, member.unit_id,
                         scaled.error());
            refuse_timed_move(*target);
            reply.send(exception_response(function, ModbusException::IllegalDataValue));
            return;
          }
          specs[reads[k].axis] = *scaled;
        }
        plan_and_send(*target, std::move(writes), std::move(specs), std::move(present), move_time_ms, function, reply,
                      std::move(after));
      });
  for (std::size_t k = 0; k < reads.size(); ++k) {
    engines_[writes[reads[k].axis].member->bus]->submit(reads[k].op, Priority::ClientRead, join->completion(k));
  }
}

void GatewayUnit::plan_and_send(SyncGroup& group, std::vector<MemberWrite> writes,
                                std::vector<modbus_map::TimedMoveSpec> specs, std::vector<std::int32_t> present,
                                std::uint16_t move_time_ms, std::uint8_t function, const Reply& reply,
                                std::function<void(const Reply&)> after) {
  struct Axis {
    const modbus_map::TimedMoveSpec* spec;
    double distance;
    double shortest;
  };
  std::vector<Axis> axes;
  std::size_t slowest = 0;
  for (std::size_t i = 0; i < writes.size(); ++i) {
    const SyncMember& member = *writes[i].member;
    const modbus_map::TimedMoveSpec* spec = &specs[i];
    const auto goal = member.map->field_bytes(*member.field, writes[i].value);
    const double distance = std::abs(static_cast<double>(field_value(*member.field, *member.map, *goal)) - present[i]);
    axes.push_back(Axis{spec, distance, modbus_map::shortest_seconds(*spec, distance)});
    if (axes[i].shortest > axes[slowest].shortest) slowest = i;
  }
  const double asked = move_time_ms / 1000.0;
  TimedMoveState plan;
  plan.limiting_unit = writes[slowest].member->unit_id;
  plan.shortest = whole_ms_up(axes[slowest].shortest);
  plan.used = std::chrono::milliseconds(move_time_ms);
  plan.result = layout::TimedMoveResult::AsAsked;
  if (axes[slowest].shortest > asked) {
    if (!group.stretch) {
      group.timed.result = layout::TimedMoveResult::Refused;
      group.timed.limiting_unit = plan.limiting_unit;
      group.timed.shortest = plan.shortest;
      group.timed.used = std::chrono::milliseconds(0);
      spdlog::info(
          "gateway unit: sync group '{}': move time {} ms refused, nothing written: unit {} needs at least {} ms "
          "for {} steps at its largest speed and acceleration (write a longer time, or configure stretch: true)",
          group.name, move_time_ms, plan.limiting_unit, plan.shortest.count(), axes[slowest].distance);
      reply.send(exception_response(function, ModbusException::IllegalDataValue));
      return;
    }
    plan.used = plan.shortest;
    plan.result = layout::TimedMoveResult::Stretched;
  }
  const double seconds = std::chrono::duration<double>(plan.used).count();
  // Every time accepted is met: an axis whose nearest profile misses it by more than 5 % (a
  // long time for a short distance: even one count of speed and of acceleration is too fast)
  // refuses the move, and the group's registers say which axis and the longest it can take.
  for (std::size_t i = 0; i < axes.size(); ++i) {
    if (axes[i].distance < 1) continue;
    const auto nearest = modbus_map::plan_axis(*axes[i].spec, axes[i].distance, seconds);
    if (!nearest || std::abs(nearest->seconds - seconds) <= kMoveTimeTolerance * seconds) continue;
    const auto longest = modbus_map::longest_seconds(*axes[i].spec, axes[i].distance);
    group.timed.result = layout::TimedMoveResult::Refused;
    group.timed.limiting_unit = writes[i].member->unit_id;
    group.timed.shortest = whole_ms_up(axes[i].shortest);
    group.timed.used = std::chrono::milliseconds(static_cast<std::int64_t>(longest * 1000.0));
    spdlog::info(
        "gateway unit: sync group '{}': move time {} ms refused, nothing written: unit {} takes at most {:.0f} ms "
        "for {} steps at its smallest speed and acceleration (write a time between {} and {:.0f} ms, or move it "
        "in a separate group)",
        group.name, plan.used.count(), writes[i].member->unit_id, longest * 1000.0, axes[i].distance,
        whole_ms_up(axes[i].shortest).count(), longest * 1000.0);
    reply.send(exception_response(function, ModbusException::IllegalDataValue));
    return;
  }
  // Goals are motion: admitted on every bus they go to once the move is known to be possible (a
  // refused move time starts no watchdog), after the reads, so the epoch is the latest.
  std::vector<MotionEpoch> epochs(engines_.size(), 0);
  std::vector<bool> admitted(engines_.size(), false);
  for (const MemberWrite& write : writes) {
    const std::size_t bus = write.member->bus;
    if (admitted[bus]) continue;
    const auto epoch = admit_or_refuse(safety_, refusal_log_, bus,
                                       "gateway unit sync group '" + group.name + "' timed move", function, reply);
    if (!epoch) {
      refuse_timed_move(group);
      return;
    }
    epochs[bus] = *epoch;
    admitted[bus] = true;
  }

  // Per member: acceleration, goal, the time field 0 (the speed governs) and speed, merged.
  std::vector<std::size_t> order(writes.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return writes[a].member->unit_id < writes[b].member->unit_id; });
  std::vector<std::vector<Block>> blocks(writes.size());
  std::vector<std::vector<modbus_map::BusWrite>> bus_writes(writes.size());
  for (const std::size_t i : order) {
    const SyncMember& member = *writes[i].member;
    const auto& table = member.map->servo_table();
    const auto& spec = *axes[i].spec;
    const auto counts = modbus_map::plan_axis(spec, axes[i].distance, seconds)
                            .value_or(modbus_map::AxisPlan{spec.max_speed, spec.max_acceleration, 0});
    std::vector<Block> parts;
    const auto add = [&](const FieldSpec& field, std::uint16_t value) {
      auto bytes = member.map->field_bytes(field, value);
      if (!bytes) return false;
      parts.push_back(Block{field.addr,
                            static_cast<std::uint16_t>(field.addr + modbus_map::address_span(table.addressing, field)),
                            std::move(*bytes)});
      return true;
    };
    bool ok = add(*member.field, writes[i].value) &&
              add(*modbus_map::field_by_name(table, spec.speed), static_cast<std::uint16_t>(counts.speed));
    if (!spec.acceleration.empty()) {
      ok = ok &&
           add(*modbus_map::field_by_name(table, spec.acceleration), static_cast<std::uint16_t>(counts.acceleration));
    }
    if (!spec.deceleration.empty()) {
      ok = ok &&
           add(*modbus_map::field_by_name(table, spec.deceleration), static_cast<std::uint16_t>(counts.acceleration));
    }
    if (!spec.time.empty()) ok = ok && add(*modbus_map::field_by_name(table, spec.time), 0);
    if (!ok) {
      spdlog::warn("gateway unit: sync group '{}' unit {}: speed {} or acceleration {} outside the table's range",
                   group.name, member.unit_id, counts.speed, counts.acceleration);
      refuse_timed_move(group);
      reply.send(exception_response(function, ModbusException::IllegalDataValue));
      return;
    }
    for (const Block& part : parts) bus_writes[i].push_back(modbus_map::BusWrite{part.address, part.bytes});
    blocks[i] = merged(std::move(parts));
  }
  // Speeds and accelerations before goals where they are separate writes (SMSMB), so each goal
  // starts its move with its own profile; unit order within each pass.
  std::vector<WriteBatch> batches;
  for (const BusEngine* engine : engines_) {
    batches.emplace_back(engine->settings().protocol != protocol::BusProtocol::ModbusRtu);
  }
  for (const bool goal_pass : {false, true}) {
    for (const std::size_t i : order) {
      const SyncMember& member = *writes[i].member;
      for (const Block& block : blocks[i]) {
        const bool has_goal = block.address <= member.field->addr && member.field->addr < block.end;
        if (has_goal == goal_pass) batches[member.bus].add(member.servo_id, block.address, block.bytes);
      }
    }
  }
  std::vector<Frame> frames;
  for (std::size_t bus = 0; bus < batches.size(); ++bus) {
    for (BusOp& op : batches[bus].frames()) {
      std::visit(
          [&](auto& each) {
            if constexpr (requires { each.motion_epoch; }) each.motion_epoch = epochs[bus];
          },
          op);
      frames.push_back(Frame{bus, std::move(op)});
    }
  }
  std::vector<HoldTarget> switched_on;
  std::vector<std::size_t> buses;
  for (std::size_t i = 0; i < writes.size(); ++i) {
    const SyncMember& member = *writes[i].member;
    if (std::find(buses.begin(), buses.end(), member.bus) == buses.end()) buses.push_back(member.bus);
    const auto& motion = modbus_map::motion_spec(member.map->servo_table().id);
    if (!modbus_map::may_enable_motion(motion, member.map->byte_order(), bus_writes[i])) continue;
    switched_on.push_back(HoldTarget{
        engines_[member.bus], member.servo_id, &motion, member.map->byte_order(),
        answers_writes(member.map->servo_table().id, member.response_level, *engines_[member.bus], member.servo_id),
        epochs[member.bus], "unit " + std::to_string(member.unit_id), std::move(bus_writes[i])});
  }
  spdlog::debug("gateway unit: sync group '{}': timed move of {} ms (asked {} ms), slowest unit {}", group.name,
                plan.used.count(), move_time_ms, plan.limiting_unit);
  send_frames(
      std::move(frames), std::move(switched_on), std::move(buses), function, reply,
      [this, target = &group, writes, plan, after = std::move(after)](const Reply& r) mutable {
        for (const MemberWrite& write : writes) record_goal(*target, write);
        plan.ends = std::chrono::steady_clock::now() + plan.used;
        target->timed = plan;
        after(r);
      },
      [target = &group] { refuse_timed_move(*target); });
}

}  // namespace sms::gateway
