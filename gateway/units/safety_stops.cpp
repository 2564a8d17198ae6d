// A safe stop: what each servo's hold needs read (one SYNC READ where the bus has it), the stop
// frames (one SYNC WRITE per write shape on packet buses), and its outcome.
#include "gateway/units/safety_impl.h"

#include <algorithm>

#include <spdlog/spdlog.h>

#include "gateway/bus/bus_join.h"
#include "gateway/bus/write_batch.h"
#include "modbus_map/tables.h"

namespace sms::gateway {

namespace {

// From the servo's answer to its context read to its stop frame's arrival: the time since the
// last answer came in, plus that answer's own wire time (the position was sampled before it was
// sent) and the stop frame's. The axis runs on that long before the frame.
double stop_lead_seconds(const BusSafety& bus, const StopTarget& target, const StopReads& read,
                         const std::vector<protocol::Bytes>& data) {
  constexpr std::size_t kFrameOverhead = 12;  // header, ID, length, checksum or CRC, on either protocol
  const std::size_t answer = (data.empty() ? 0 : data.back().size()) + kFrameOverhead;
  const std::size_t frame = std::size_t{modbus_map::goal_block(*target.spec).count} *
                                modbus_map::bytes_per_address(modbus_map::table(target.spec->table).addressing) +
                            kFrameOverhead;
  const SerialSettings& serial = bus.engine->settings().serial;
  const double wire = static_cast<double>(answer + frame) * serial.bits_per_character() / serial.baud;
  return std::chrono::duration<double>(Clock::now() - read.answered).count() + wire;
}

std::string targets_text(const std::vector<std::string>& parts) {
  std::string text;
  for (const auto& part : parts) {
    if (!text.empty()) text += "; ";
    text += part;
  }
  return text;
}

}  // namespace

// Safety thread. Reads what the holds need, then sends the stop frames; `done(ok)` after the
// last frame (ok: every servo was reached).
void SafetySupervisor::Impl::run_stop(std::size_t index, StopCause cause, std::optional<StopAction> override,
                                      Clock::time_point since, const std::string& reason,
                                      const std::function<void(bool)>& done, std::optional<std::uint8_t> only) {
  BusSafety& bus = *buses_[index];
  auto contexts = std::make_shared<Contexts>();
  auto write_phase = [this, index, cause, override, since, reason, done, contexts, only] {
    send_stop_frames(index, cause, override, since, reason, done, *contexts, only);
  };
  // Targets whose whole state is one range of a table with SYNC READ are read in one frame per
  // range (a 60-servo arm: one frame instead of 60 READs); the rest, one READ per range. A servo
  // known to be offline is left out of the SYNC READ: the frame would wait a whole response
  // timeout for it; its own READ is answered at once (offline) and it is owed its stop.
  std::map<std::pair<std::uint16_t, std::uint16_t>, std::vector<std::size_t>> by_range;
  std::vector<std::size_t> singly;
  for (std::size_t t = 0; t < bus.targets.size(); ++t) {
    const StopTarget& target = bus.targets[t];
    if (only && target.servo_id != *only) continue;
    if (override.value_or(target.action) != StopAction::Hold) continue;
    const auto cached = bus.engine->cache().state(target.servo_id);
    const bool known_offline = bus.engine->discovered() && cached && !cached->online;
    if (bus.sync_read && !known_offline && target.context.size() == 1 &&
        modbus_map::table(target.spec->table).has_sync_read) {
      by_range[{target.context[0].address, target.context[0].count}].push_back(t);
    } else {
      singly.push_back(t);
    }
  }
  std::vector<std::pair<modbus_map::BusRange, std::vector<std::size_t>>> groups;
  for (auto& [range, members] : by_range) {
    if (members.size() == 1) {
      singly.push_back(members[0]);
    } else {
      groups.push_back({modbus_map::BusRange{range.first, range.second}, std::move(members)});
    }
  }
  if (groups.empty()) {
    read_contexts(bus, singly, contexts, write_phase);
    return;
  }
  // Whoever stayed silent in a SYNC READ is read on its own, with the bus's retries, before the
  // frames go out: one missed answer must not turn a hold into a torque off.
  std::vector<SyncReadOp> frames;
  for (const auto& [range, members] : groups) {
    SyncReadOp frame{range.address, range.count, {}};
    for (const std::size_t t : members) frame.ids.push_back(bus.targets[t].servo_id);
    frames.push_back(std::move(frame));
  }
  auto join =
      BusJoin::create(groups.size(), run_here(),
                      [this, index, groups, frames, singly, contexts, write_phase](std::vector<BusResult> results) {
                        std::vector<std::size_t> again = singly;
                        for (std::size_t g = 0; g < groups.size(); ++g) {
                          const auto answers = sync_read_answers(frames[g], results[g]);
                          const auto& members = groups[g].second;
                          for (std::size_t m = 0; m < members.size(); ++m) {
                            if (answers[m]) {
                              StopReads& read = (*contexts)[members[m]];
                              read.results.push_back(BusResult{BusStatus::Ok, 0, *answers[m], {}});
                              read.answered = Clock::now();
                            } else {
                              again.push_back(members[m]);
                            }
                          }
                        }
                        read_contexts(*buses_[index], again, contexts, write_phase);
                      });
  for (std::size_t g = 0; g < frames.size(); ++g) submit_safely(bus, frames[g], join->completion(g));
}

// Reads every context range of `targets` into `contexts`, then `then()`. The completions run
// where the last read completes (the bus thread), so the next phase is queued before the engine
// picks its next job: a poll due meanwhile cannot slip in between.
void SafetySupervisor::Impl::read_contexts(BusSafety& bus, const std::vector<std::size_t>& targets,
                                           const std::shared_ptr<Contexts>& contexts,
                                           const std::function<void()>& then) {
  std::vector<std::pair<std::size_t, modbus_map::BusRange>> reads;
  for (const std::size_t t : targets) {
    for (const auto& range : bus.targets[t].context) reads.emplace_back(t, range);
  }
  if (reads.empty()) {
    then();
    return;
  }
  auto answered = std::make_shared<std::vector<Clock::time_point>>(reads.size());
  auto join =
      BusJoin::create(reads.size(), run_here(), [reads, contexts, answered, then](std::vector<BusResult> results) {
        for (std::size_t i = 0; i < reads.size(); ++i) {
          StopReads& read = (*contexts)[reads[i].first];
          read.results.push_back(std::move(results[i]));
          read.answered = std::max(read.answered, (*answered)[i]);
        }
        then();
      });
  for (std::size_t i = 0; i < reads.size(); ++i) {
    const StopTarget& target = bus.targets[reads[i].first];
    submit_safely(bus, ReadOp{target.servo_id, reads[i].second.address, reads[i].second.count},
                  [answered, i, completion = join->completion(i)](BusResult result) {
                    (*answered)[i] = Clock::now();
                    completion(std::move(result));
                  });
  }
}

void SafetySupervisor::Impl::send_stop_frames(std::size_t index, StopCause cause, std::optional<StopAction> override,
                                              Clock::time_point since, const std::string& reason,
                                              const std::function<void(bool)>& done, const Contexts& context,
                                              std::optional<std::uint8_t> only) {
  BusSafety& bus = *buses_[index];
  std::vector<std::string> report;
  WriteBatch batch(bus.packet);                         // one SYNC WRITE per write shape on packet buses
  std::vector<std::vector<std::size_t>> frame_targets;  // the targets each frame reaches
  std::vector<std::size_t> unconfirmed;                 // torque off broadcast blind: owed until acknowledged
  const auto add_write = [&](std::size_t t, modbus_map::BusWrite write) {
    const std::size_t frame = batch.add(bus.targets[t].servo_id, write.address, std::move(write.data));
    if (frame_targets.size() <= frame) frame_targets.resize(frame + 1);
    frame_targets[frame].push_back(t);
  };
  for (std::size_t t = 0; t < bus.targets.size(); ++t) {
    const StopTarget& target = bus.targets[t];
    if (only && target.servo_id != *only) continue;
    const StopAction action = override.value_or(target.action);
    const std::string who = "servo " + std::to_string(target.servo_id);
    if (action == StopAction::None) {
      report.push_back(who + " none");
      continue;
    }
    if (action == StopAction::TorqueOff) {
      add_write(t, modbus_map::torque_off_write(*target.spec, target.order));
      report.push_back(who + " torque off");
      continue;
    }
    std::vector<protocol::Bytes> data;
    std::string failure;
    double lead_seconds = 0;
    const auto found = context.find(t);
    if (found != context.end()) {
      for (const BusResult& result : found->second.results) {
        if (result.status != BusStatus::Ok) {
          failure = result.detail.empty() ? std::string(gateway::to_string(result.status)) : result.detail;
          break;
        }
        data.push_back(result.data);
      }
      lead_seconds = stop_lead_seconds(bus, target, found->second, data);
    }
    Expected<modbus_map::SafeStopPlan> plan = unexpected(failure);
    if (failure.empty()) {
      plan =
          modbus_map::plan_safe_stop(*target.spec, action, target.order, modbus_map::StopContext{target.context, data},
                                     modbus_map::StopOptions{.torque_known_on = false,
                                                             .deceleration = target.stop_deceleration,
                                                             .keep_ramp = false,
                                                             .lead_seconds = lead_seconds});
    }
    if (!plan) {
      // Without its state no hold can be computed; an unknown motion must still end.
      spdlog::error("safety: bus {}: {}: cannot hold it ({}); switching its torque off instead", bus.name, who,
                    plan.error());
      add_write(t, modbus_map::torque_off_write(*target.spec, target.order));
      if (bus.packet) unconfirmed.push_back(t);
      report.push_back(who + " torque off (state unreadable)");
      continue;
    }
    for (auto& write : plan->writes) add_write(t, std::move(write));
    report.push_back(who + " " + plan->what);
  }

  std::vector<BusOp> frames = std::move(batch.frames());
  const auto finish = [this, index, cause, since, reason, done, report, frame_targets, unconfirmed,
                       only](const std::vector<BusResult>& results) {
    BusSafety& b = *buses_[index];
    // Who the stop did not reach: every servo of a frame that failed, and on packet buses those
    // whose torque off went out blind (a broadcast is never acknowledged).
    std::vector<std::size_t> unreached = unconfirmed;
    std::string failure;
    for (std::size_t i = 0; i < results.size(); ++i) {
      if (results[i].status == BusStatus::Ok) continue;
      if (failure.empty())
        failure = results[i].detail.empty() ? std::string(to_string(results[i].status)) : results[i].detail;
      unreached.insert(unreached.end(), frame_targets[i].begin(), frame_targets[i].end());
    }
    std::sort(unreached.begin(), unreached.end());
    unreached.erase(std::unique(unreached.begin(), unreached.end()), unreached.end());
    const bool frames_ok = failure.empty();
    const std::string owed = owe_stops(b, unreached, reason);
    const auto latency = std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - since);
    if (only) {
      // One servo's hold (an operator's hold-to-run released): not a stop of the bus.
      if (frames_ok) {
        spdlog::info("safety: bus {}: {} ({}): {}", b.name, reason, targets_text(report),
                     report.empty() ? "no such servo on the bus" : "sent");
      } else {
        spdlog::error("safety: bus {}: {} FAILED: {}; planned: {}{}", b.name, reason, failure, targets_text(report),
                      owed.empty() ? std::string() : "; servo " + owed + " is owed its stop (torque off)");
      }
      if (done) done(frames_ok && !report.empty());
      return;
    }
    b.last_cause.store(cause);
    if (frames_ok) {
      b.stops.fetch_add(1);
      b.last_latency_us.store(latency.count());
      spdlog::warn("safety: bus {}: safe stop ({}) sent {:.1f} ms after {}: {}{}", b.name, reason,
                   static_cast<double>(latency.count()) / 1000.0,
                   cause == StopCause::Watchdog ? "the last feed" : "the request", targets_text(report),
                   owed.empty() ? std::string()
                                : "; not confirmed for servo(s) " + owed +
                                      " (state unreadable): their torque off is owed until they acknowledge it");
    } else {
      b.failed_stops.fetch_add(1);
      b.last_latency_us.store(-1);
      spdlog::error(
          "safety: bus {}: safe stop ({}) FAILED: {}; planned: {}; servo(s) {} are owed their stop (torque "
          "off): it is sent the moment they can be reached, before anything else, and motion writes to "
          "them are refused until they have taken it",
          b.name, reason, failure, targets_text(report), owed);
    }
    if (done) done(frames_ok);
  };
  if (frames.empty()) {
    finish({});
    return;
  }
  auto join = BusJoin::create(frames.size(), safety_post(), finish);
  for (std::size_t i = 0; i < frames.size(); ++i) submit_safely(bus, std::move(frames[i]), join->completion(i));
}

// A stop must not die on an operation the bus refuses to express (a programming error):
// it becomes that operation's failure, said in the stop's log line.
void SafetySupervisor::Impl::submit_safely(BusSafety& bus, BusOp op, const Completion& done) {
  try {
    bus.engine->submit(std::move(op), Priority::Safety, done);
  } catch (const std::exception& error) {
    done(BusResult{BusStatus::Dropped, 0, {}, "bus " + bus.name + ": " + error.what()});
  }
}

}  // namespace sms::gateway
