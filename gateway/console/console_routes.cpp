#include "gateway/console/console_routes.h"

#include <algorithm>
#include <array>

#include <spdlog/spdlog.h>

#include "gateway/console/console_commission.h"
#include "gateway/console/console_view.h"
#include "gateway/service/modbus_request.h"
#include "gateway/units/gateway_unit.h"
#include "modbus_map/eeprom_lock.h"
#include "modbus_map/motion.h"
#include "modbus_map/status_bits.h"
#include "protocol/modbus_pdu.h"

namespace sms::gateway::console {

namespace {

using config::Role;
using nlohmann::json;

std::string role_text(Role role) { return std::string(config::to_string(role)); }

Bytes write_register_pdu(std::uint16_t address, std::uint16_t value) {
  return request_pdu(WriteRegistersRequest{function_code::kWriteSingleRegister, address, {value}});
}
Bytes write_coil_pdu(std::uint16_t address, bool on) {
  return request_pdu(WriteBitsRequest{function_code::kWriteSingleCoil, address, {on}});
}
Bytes read_registers_pdu(std::uint16_t address, std::uint16_t count) {
  return request_pdu(ReadRegistersRequest{function_code::kReadHoldingRegisters, address, count});
}
std::vector<std::uint16_t> registers_in(const Bytes& pdu) {
  std::vector<std::uint16_t> values;
  for (std::size_t i = 2; i + 1 < pdu.size(); i += 2)
    values.push_back(static_cast<std::uint16_t>(pdu[i] << 8 | pdu[i + 1]));
  return values;
}

// HTTP status for a Modbus exception: the role gate's refusals 403, the router's by their code.
unsigned status_for(const ModbusAnswer& answer) {
  if (answer.role_refused) return 403;
  switch (answer.exception) {
    case 0x01: return 403;  // a function the console may not use
    case 0x02:
    case 0x03: return 400;
    case 0x04: return 409;  // motion blocked, or the servo refused
    case 0x06: return 503;
    case 0x0A: return 502;
    case 0x0B: return 504;
    default: return 500;
  }
}

std::string units_list(const Services& services) {
  std::string text;
  for (const auto& servo : services.config().servos) {
    if (services.units().servo_unit(servo.unit_id) == nullptr) continue;
    text += (text.empty() ? "" : ", ") + std::to_string(servo.unit_id);
  }
  return text.empty() ? "none" : text;
}

// The servo unit named by the {unit} parameter, or the answer saying why not.
Expected<const ServoUnit*, HttpAnswer> servo_of(Services& services, const PathParams& params) {
  const auto text = params.get("unit").value_or("");
  const auto unit_id = parse_unit(text);
  const ServoUnit* unit = unit_id ? services.units().servo_unit(*unit_id) : nullptr;
  if (unit == nullptr) {
    return unexpected(
        HttpAnswer::error(404, "unit " + printable(text) +
                                   " is not a servo unit of this gateway (servo units: " + units_list(services) + ")"));
  }
  return unit;
}

// The servo page of a unit that is no servo unit: the API's 404.
std::optional<HttpAnswer> servo_page_missing(Services& services, const PathParams& params) {
  auto unit = servo_of(services, params);
  if (unit) return std::nullopt;
  return unit.error();
}

// --- pages' JSON ------------------------------------------------------------------------------

void api_session(const std::shared_ptr<ApiCall>& call) {
  if (!call->session || call->who.role == Role::None) {
    json body = {{"error", "log in first"}, {"login", true}};
    return call->answer(HttpAnswer::json(401, body));
  }
  call->answer(HttpAnswer::json(200, {{"user", call->who.name},
                                      {"role", role_text(call->who.role)},
                                      {"how", call->who.how},
                                      {"csrf", call->session->csrf},
                                      {"logout", call->who.how == "password"}}));
}

void api_login(const std::shared_ptr<ApiCall>& call) {
  const auto request = parse_login(call->body);
  if (!request) return call->answer(HttpAnswer::error(400, "login: " + request.error()));
  if (call->services.settings().users.empty()) {
    return call->answer(HttpAnswer::error(404, "this console has no users (console.users); nothing to log in to"));
  }
  // The password check takes ~100 ms of CPU: it runs on the login worker, and the answer comes
  // back to this thread (login_guard.h); failed logins are logged there, at most once a second.
  call->services.login(call->peer_address, request->user, request->password, [call](LoginOutcome outcome) {
    using Result = LoginOutcome::Result;
    if (outcome.result == Result::Throttled || outcome.result == Result::Busy) {
      HttpAnswer answer =
          HttpAnswer::json(outcome.result == Result::Throttled ? 429 : 503,
                           {{"error", outcome.message}, {"retry_after_s", outcome.retry_after.count()}});
      answer.headers.emplace_back("Retry-After", std::to_string(outcome.retry_after.count()));
      return call->answer(std::move(answer));
    }
    if (outcome.result != Result::Ok || !outcome.who) {
      return call->answer(HttpAnswer::error(401, outcome.message));
    }
    const Principal& who = *outcome.who;
    // The old session's CSRF token goes stale with it.
    if (call->session) call->services.sessions().remove(call->session->token);
    const Session session = call->services.sessions().create(who);
    spdlog::info("console: user `{}` logged in ({})", who.name, role_text(who.role));
    HttpAnswer answer =
        HttpAnswer::json(200, {{"user", who.name}, {"role", role_text(who.role)}, {"csrf", session.csrf}});
    answer.headers.emplace_back("Set-Cookie", call->services.session_cookie(session.token));
    call->answer(std::move(answer));
  });
}

void api_logout(const std::shared_ptr<ApiCall>& call) {
  if (call->session) call->services.sessions().remove(call->session->token);
  HttpAnswer answer = HttpAnswer::json(200, {{"ok", true}});
  answer.headers.emplace_back("Set-Cookie", call->services.session_cookie(""));
  call->answer(std::move(answer));
}

void api_overview(const std::shared_ptr<ApiCall>& call) {
  call->answer(HttpAnswer::json(200, call->services.overview()));
}

// The table with the value of every readable field, read live through the router: one FC03 per
// run the map accepts (RegisterMap::live_read_runs: an smsmb table's gaps answer 0x02), in turn.
struct ServoRead {
  std::shared_ptr<ApiCall> call;
  const ServoUnit* unit;
  json body;
  json values = json::object();
  std::vector<modbus_map::BusRange> runs;
  std::size_t next = 0;
};

void read_next_run(const std::shared_ptr<ServoRead>& read) {
  if (read->next == read->runs.size()) {
    read->body["values"] = std::move(read->values);
    return read->call->answer(HttpAnswer::json(200, read->body));
  }
  const modbus_map::BusRange run = read->runs[read->next++];
  read->call->services.modbus(read->call->who, read->unit->unit_id, read_registers_pdu(run.address, run.count),
                              [read, run](const ModbusAnswer& answer) {
                                if (!answer.ok()) {
                                  // The values read so far stay; the rest are missing, and the page says why.
                                  read->body["values_error"] = answer.message;
                                  read->next = read->runs.size();
                                  return read_next_run(read);
                                }
                                const auto registers = registers_in(answer.pdu);
                                for (const auto& entry : read->unit->map.entries()) {
                                  if (!entry.readable || entry.address < run.address) continue;
                                  const std::size_t at = std::size_t{entry.address} - run.address;
                                  if (at >= registers.size()) continue;
                                  read->values[std::string(entry.shown->name)] =
                                      register_to_value(entry, registers[at]);
                                }
                                read_next_run(read);
                              });
}

void api_servo(const std::shared_ptr<ApiCall>& call) {
  const auto unit = servo_of(call->services, call->params);
  if (!unit) return call->answer(unit.error());
  auto read = std::make_shared<ServoRead>();
  read->call = call;
  read->unit = *unit;
  read->body = servo_description_json(call->services.config(), **unit);
  std::vector<const modbus_map::RegisterEntry*> readable;
  for (const auto& entry : (*unit)->map.entries()) {
    if (entry.readable && entry.address < modbus_map::kStagedWriteBase) readable.push_back(&entry);
  }
  std::sort(readable.begin(), readable.end(), [](auto* a, auto* b) { return a->address < b->address; });
  read->runs = (*unit)->map.live_read_runs(readable);
  read_next_run(read);
}

// The register that shows the table's EEPROM lock (modbus_map/eeprom_lock.h), or nullptr.
const modbus_map::RegisterEntry* eeprom_lock(const ServoUnit& unit) {
  const auto* lock = modbus_map::eeprom_lock(unit.map.servo_table());
  return lock == nullptr ? nullptr : entry_for_servo_field(unit.map, lock->name);
}

// Writes `steps` one after another. After a refusal the rest are skipped, but for those that
// run whatever came before (the lock put back); `done` gets the first failure and its step.
struct WriteStep {
  std::uint16_t address;
  std::uint16_t value;
  std::string what;
  bool even_after_a_failure = false;
};
struct FailedStep {
  ModbusAnswer answer;
  std::string what;
};
void run_steps(Services& services, const Principal& who, std::uint8_t unit, std::vector<WriteStep> steps,
               std::size_t index, std::optional<FailedStep> failed,
               std::function<void(std::optional<FailedStep>)> done) {
  while (failed && index < steps.size() && !steps[index].even_after_a_failure) ++index;
  if (index == steps.size()) return done(std::move(failed));
  const Bytes pdu = write_register_pdu(steps[index].address, steps[index].value);
  services.modbus(who, unit, pdu,
                  [&services, who, unit, steps = std::move(steps), index, failed = std::move(failed),
                   done = std::move(done)](ModbusAnswer answer) mutable {
                    if (!answer.ok() && !failed) failed = FailedStep{std::move(answer), steps[index].what};
                    run_steps(services, who, unit, std::move(steps), index + 1, std::move(failed), std::move(done));
                  });
}

}  // namespace

Expected<CheckedFieldWrite, HttpAnswer> check_field_write(const ServoUnit& unit, std::string_view field,
                                                          std::int64_t value) {
  const auto* entry = entry_named(unit.map, field);
  if (entry == nullptr) {
    return unexpected(HttpAnswer::error(
        400, "no field `" + printable(field) + "` in " + unit.map.description() + "; nothing written"));
  }
  const std::string name(entry->shown->name);
  if (unit.read_only) {
    return unexpected(HttpAnswer::error(400, name + " cannot be written (the unit is read_only); nothing written"));
  }
  if (commissioning_only(name)) {
    return unexpected(HttpAnswer::error(400, name + " takes the servo off this bus: change it with `sms-gateway " +
                                                 (name == "id" ? "set-id" : "set-baud") +
                                                 "` on a line no bus owns (docs/HARDWARE.md); nothing written"));
  }
  const auto checked = unit.map.check_write(*entry, value);
  if (!checked) {
    return unexpected(HttpAnswer::error(400, modbus_map::to_string(checked.error()) + "; nothing written"));
  }
  return CheckedFieldWrite{entry, *checked};
}

namespace {

// A 0x04 answer says which rule refused (UnitRouter::refusal_reason, as the Sparkplug node says it).
std::string refusal_text(const Services& services, const ServoUnit& unit, const ModbusAnswer& answer) {
  if (answer.exception != 0x04) return answer.message;
  const auto reason = services.units().refusal_reason(unit);
  return reason.safety_rule ? reason.text : reason.text + "; " + answer.message;
}

void api_servo_write(const std::shared_ptr<ApiCall>& call) {
  const auto unit = servo_of(call->services, call->params);
  if (!unit) return call->answer(unit.error());
  const auto request = parse_field_write(call->body);
  if (!request) return call->answer(HttpAnswer::error(400, request.error() + "; nothing written"));
  const ServoUnit& servo = **unit;
  const auto checked = check_field_write(servo, request->field, request->value);
  if (!checked) return call->answer(checked.error());
  const auto* entry = checked->entry;
  const std::string name(entry->shown->name);
  const std::int64_t value = request->value;
  const std::uint16_t reg = checked->value.register_value;
  // The role before anything is sent: an EEPROM write's unlock would otherwise be what is refused.
  if (const auto refused = call->services.refusal(call->who, servo.unit_id, write_register_pdu(entry->address, reg))) {
    return call->answer(HttpAnswer::error(403, name + ": " + refused->text() + "; nothing written"));
  }
  std::vector<WriteStep> steps{{entry->address, reg, name + " := " + std::to_string(value)}};
  const auto* lock = eeprom_lock(servo);
  const bool eeprom = checked->value.servo_field->area == modbus_map::Area::Eeprom;
  auto finish = [call, name, value, unit = *unit](std::optional<FailedStep> failed) {
    if (failed) {
      return call->answer(HttpAnswer::error(status_for(failed->answer),
                                            failed->what + ": " + refusal_text(call->services, *unit, failed->answer)));
    }
    call->answer(HttpAnswer::json(200, {{"ok", true}, {"field", name}, {"value", value}}));
  };
  if (!eeprom || lock == nullptr || entry == lock) {
    return run_steps(call->services, call->who, servo.unit_id, std::move(steps), 0, std::nullopt, std::move(finish));
  }
  // EEPROM with a lock, as the tools write it (modbus_map/eeprom_lock.h): read it; closed, open it
  // for the write and put it back after, also when the write failed.
  call->services.modbus(
      call->who, servo.unit_id, read_registers_pdu(lock->address, 1),
      [call, steps = std::move(steps), lock, unit_id = servo.unit_id, finish](ModbusAnswer answer) mutable {
        if (!answer.ok()) return finish(FailedStep{std::move(answer), "reading the EEPROM lock"});
        const modbus_map::EepromUnlock unlock{lock->counterpart, registers_in(answer.pdu).at(0)};
        if (unlock.needed()) {
          steps.insert(steps.begin(), WriteStep{lock->address, static_cast<std::uint16_t>(modbus_map::kEepromUnlocked),
                                                unlock.unlock_text()});
          steps.push_back(
              WriteStep{lock->address, static_cast<std::uint16_t>(unlock.read), unlock.relock_text(), true});
        }
        run_steps(call->services, call->who, unit_id, std::move(steps), 0, std::nullopt, finish);
      });
}

void gateway_coil(const std::shared_ptr<ApiCall>& call, std::uint16_t coil, bool on, std::string what) {
  call->services.modbus(call->who, call->services.config().modbus_tcp.gateway_unit_id, write_coil_pdu(coil, on),
                        [call, what = std::move(what)](const ModbusAnswer& answer) {
                          if (!answer.ok()) {
                            return call->answer(HttpAnswer::error(status_for(answer), what + ": " + answer.message));
                          }
                          call->answer(HttpAnswer::json(200, {{"ok", true}, {"done", what}}));
                        });
}

void api_estop(const std::shared_ptr<ApiCall>& call) {
  const auto request = parse_estop(call->body);
  if (!request) return call->answer(HttpAnswer::error(400, "e-stop: " + request.error()));
  gateway_coil(call, gateway_unit_layout::kEStopCoil, request->latch,
               request->latch ? "e-stop latched" : "e-stop reset");
}

void api_rearm(const std::shared_ptr<ApiCall>& call) {
  gateway_coil(call, gateway_unit_layout::kWatchdogCoil, false, "watchdogs re-armed");
}

// --- streams ------------------------------------------------------------------------------------

class OverviewStream final : public Stream {
 public:
  explicit OverviewStream(Services& services) : services_(services) {}
  std::optional<std::string> flush(SteadyClock::time_point) override {
    std::string text = services_.overview().dump();
    if (text == last_) return std::nullopt;
    last_ = text;
    return text;
  }

 private:
  Services& services_;
  std::string last_;
};

Expected<std::unique_ptr<Stream>> make_overview_stream(Services& services, const PathParams&, const Principal&) {
  return std::unique_ptr<Stream>(std::make_unique<OverviewStream>(services));
}

// A servo page: every new poll of the servo (its whole poll block, at the poll rate) batched
// per push period, and the jog panel's hold-to-run moves (position and speed), each a JogSession
// from its press to its end (console_jog.h).
class ServoStream final : public Stream {
 public:
  ServoStream(Services& services, const ServoUnit& unit, Principal who)
      : services_(services),
        unit_(unit),
        who_(std::move(who)),
        spec_(modbus_map::motion_spec(unit.map.servo_table().id)),
        goal_position_(entry_for_servo_field(unit.map, spec_.goal_position)),
        goal_speed_(entry_for_servo_field(unit.map, spec_.goal_speed)),
        torque_(entry_for_servo_field(unit.map, spec_.torque)),
        mode_(spec_.mode.empty() ? nullptr : entry_for_servo_field(unit.map, spec_.mode)),
        bus_name_(services.config().buses.at(unit.bus_index).name),
        alive_(std::make_shared<bool>(true)) {}
  ~ServoStream() override { *alive_ = false; }

  void sample(SteadyClock::time_point now) override {
    end_jog_if_stopped();
    if (jog_ && now - last_heartbeat_ > kJogHeartbeatTimeout)
      end_jog("no heartbeat from the page for " + std::to_string(kJogHeartbeatTimeout.count()) + " ms");
    if (jog_ && now - last_refresh_ >= kJogRefreshPeriod) {
      last_refresh_ = now;
      write_jog_goal();
    }
    // Every 10 ms, and a poll comes every poll period: the block is decoded only when it is new.
    const auto state = unit_.engine->cache().state(unit_.servo_id);
    if (!state || !state->has_data || state->updated == last_sample_) return;
    const auto polled = read_polled(unit_);
    if (!polled || !polled->has_data || polled->updated == last_sample_) return;
    last_sample_ = polled->updated;
    if (names_.empty()) {
      for (const auto& [entry, value] : polled->values) names_.emplace_back(entry->shown->name);
    }
    json row = json::array();
    row.push_back(steady_us(polled->updated));
    for (const auto& [entry, value] : polled->values) row.push_back(value);
    samples_.push_back(std::move(row));
    online_ = polled->online;
    status_ = polled->status;
  }

  std::optional<std::string> flush(SteadyClock::time_point now) override {
    if (samples_.empty() && !state_changed_) return std::nullopt;
    json message = {{"type", "samples"},
                    {"unit", unit_.unit_id},
                    {"fields", names_},
                    {"samples", std::move(samples_)},
                    {"online", online_},
                    {"status", status_},
                    {"faults", modbus_map::status_faults(unit_.map.servo_table().id, status_)},
                    {"jog", jog_ ? (jog_speed_ ? "speed" : "position") : "stopped"},
                    {"jog_reason", jog_reason_},
                    {"sent_us", steady_us(now)}};
    samples_ = json::array();
    state_changed_ = false;
    return message.dump();
  }

  void on_message(std::string_view text, const Send& send) override {
    const auto message = parse_jog_message(text);
    if (!message) return send(json{{"type", "error"}, {"message", message.error()}}.dump());
    const auto now = SteadyClock::now();
    using Kind = JogMessage::Kind;
    if (message->kind == Kind::Heartbeat) {
      last_heartbeat_ = now;
      return;
    }
    if (message->kind == Kind::Release) {
      ++jog_generation_;  // a speed jog still waiting for its mode check does not start
      return stop_jog("released");
    }
    if (!role_allows(who_.role, Role::Operate)) {
      return send(
          json{{"type", "error"},
               {"message", "the jog panel needs the operate role; " + who_.name + " has " + role_text(who_.role)}}
              .dump());
    }
    if (message->kind == Kind::Torque) {
      if (torque_ == nullptr) return send(error_json("this table has no torque switch"));
      return write(torque_->address, message->on ? 1 : 0, message->on ? "torque on" : "torque off", send);
    }
    const bool speed = message->kind == Kind::JogSpeed;
    const auto* entry = speed ? goal_speed_ : goal_position_;
    if (entry == nullptr)
      return send(error_json(std::string("this table has no ") + (speed ? "goal speed" : "goal position")));
    if (const auto checked = unit_.map.check_write(*entry, message->value); !checked) {
      return send(error_json(modbus_map::to_string(checked.error()) + "; not moved"));
    }
    // A press: a new session, with the bus's motion stops as they are now; a move still running
    // from an earlier press ends first if a stop came since (it would end at the next sample).
    ++jog_generation_;  // a speed jog of an earlier press still waiting for its mode check does not start
    end_jog_if_stopped();
    auto session = JogSession::press(unit_.bus_index, bus_name_, services_.motion_stops(unit_.bus_index));
    if (!session) return send(error_json(session.error()));
    if (!speed || mode_ == nullptr) return start_jog(speed, message->value, std::move(*session), send, now);
    // A speed goal turns only a servo in a speed mode (in position mode it is the move's speed
    // limit and nothing turns): read its mode first, and say so rather than do nothing.
    services_.modbus(who_, unit_.unit_id, read_registers_pdu(mode_->address, 1),
                     [this, alive = alive_, generation = jog_generation_, value = message->value,
                      session = std::move(*session), send](const ModbusAnswer& answer) {
                       if (!*alive || generation != jog_generation_) return;
                       if (!answer.ok())
                         return send(error_json("reading " + std::string(spec_.mode) + ": " + answer.message));
                       const std::int64_t mode = static_cast<std::int16_t>(registers_in(answer.pdu).at(0));
                       const auto drive = std::find_if(spec_.modes.begin(), spec_.modes.end(),
                                                       [mode](const auto& entry) { return entry.value == mode; });
                       if (drive == spec_.modes.end() || drive->drive != modbus_map::Drive::Velocity) {
                         return send(error_json("servo " + std::to_string(unit_.unit_id) + " is not in a speed mode (" +
                                                std::string(spec_.mode) + " = " + std::to_string(mode) +
                                                "): the speed jog turns a servo in wheel mode; set " +
                                                std::string(spec_.mode) + " in the control table first; not moved"));
                       }
                       start_jog(true, value, session, send, SteadyClock::now());
                     });
  }

  void on_close() override { stop_jog("the page went away"); }

 private:
  static std::string error_json(std::string message) {
    return json{{"type", "error"}, {"message", std::move(message)}}.dump();
  }

  void write(std::uint16_t address, std::int64_t value, std::string what, const Send& send) {
    const auto reg = static_cast<std::uint16_t>(static_cast<std::int16_t>(value));
    services_.modbus(
        who_, unit_.unit_id, write_register_pdu(address, reg),
        [this, send, what = std::move(what), alive = alive_](const ModbusAnswer& answer) {
          if (!*alive || !send) return;
          if (answer.ok()) return send(json{{"type", "done"}, {"message", what}}.dump());
          send(json{{"type", "error"}, {"message", what + ": " + refusal_text(services_, unit_, answer)}}.dump());
        });
  }

  void start_jog(bool speed, std::int64_t value, JogSession session, const Send& send, SteadyClock::time_point now) {
    // A stop during the speed jog's mode check ends the session before it moved.
    if (const auto why = session.ended(services_.motion_stops(unit_.bus_index))) return send(error_json(*why));
    session_ = std::move(session);
    jog_writes_->hold_owed = false;  // pressed again before the last stop went: its write follows the old ones
    jog_ = true;
    jog_speed_ = speed;
    jog_value_ = value;
    jog_reason_ = "held";
    state_changed_ = true;
    last_heartbeat_ = now;
    last_refresh_ = now;
    send_ = send;
    write_jog_goal();
  }

  // The goal of the session's move, checked against its press once more on the io thread.
  void write_jog_goal() {
    const auto* entry = jog_speed_ ? goal_speed_ : goal_position_;
    ++jog_writes_->in_flight;
    services_.jog_modbus(
        who_, unit_.unit_id,
        write_register_pdu(entry->address, static_cast<std::uint16_t>(static_cast<std::int16_t>(jog_value_))),
        *session_,
        [this, alive = alive_, generation = jog_generation_, writes = jog_writes_, services = &services_, who = who_,
         unit = &unit_](const ModbusAnswer& answer) {
          // The stop waited for this write (stop_jog); it goes now, after it, even if the page is gone.
          if (--writes->in_flight == 0 && writes->hold_owed) {
            writes->hold_owed = false;
            send_hold(*services, who, *unit);
          }
          if (!*alive || answer.ok() || !jog_ || generation != jog_generation_) return;
          // Refused (a stop since the press, e-stop, watchdog) or lost (a timeout): the move is
          // over, and the goal an earlier write set must not carry it on.
          if (!end_jog_if_stopped()) end_jog("the goal write failed: " + answer.message);
        });
  }

  // The safety rule of the running move (console_jog.h): true when a stop since its press ended it.
  bool end_jog_if_stopped() {
    if (!jog_) return false;
    const auto why = session_->ended(services_.motion_stops(unit_.bus_index));
    if (!why) return false;
    end_jog(*why);
    return true;
  }

  // The gateway ends the move (not the page): stopped as on a release, and the page is told why
  // and lets go of its hold, so moving again takes a new press.
  void end_jog(std::string reason) {
    if (!jog_) return;
    ++jog_generation_;
    stop_jog(reason);
    if (send_) send_(json{{"type", "jog_ended"}, {"message", std::move(reason)}}.dump());
  }

  // The servo's safe stop `hold`, as every stop path writes it (SafetySupervisor::hold_servo): read
  // live, speed moves get speed 0 and position moves goal := present position, with the stop
  // ramp in the same frame, so the jog's ramp cannot carry the axis on and back. It goes after
  // every goal write of the jog still on its way: a refresh sent just before the release would
  // otherwise land after the hold and carry the axis on to the jog's goal.
  void stop_jog(std::string reason) {
    if (!jog_) return;
    jog_ = false;
    jog_reason_ = std::move(reason);
    state_changed_ = true;
    spdlog::info("console: hold-to-run on unit {} stopped ({}) for {}", unit_.unit_id, jog_reason_, who_.name);
    if (jog_writes_->in_flight > 0) {
      jog_writes_->hold_owed = true;
      return;
    }
    send_hold(services_, who_, unit_);
  }

  static void send_hold(Services& services, const Principal& who, const ServoUnit& unit) {
    services.hold_servo(who, unit, [unit = unit.unit_id](bool ok) {
      if (!ok)
        spdlog::warn("console: the hold-to-run stop of unit {} did not reach the servo (the log says why)", unit);
    });
  }

  Services& services_;
  const ServoUnit& unit_;
  const Principal who_;
  const modbus_map::MotionSpec& spec_;
  const modbus_map::RegisterEntry* goal_position_;
  const modbus_map::RegisterEntry* goal_speed_;
  const modbus_map::RegisterEntry* torque_;
  const modbus_map::RegisterEntry* mode_;  // the operating-mode field; nullptr: the table has none
  const std::string bus_name_;
  std::shared_ptr<bool> alive_;
  std::vector<std::string> names_;
  json samples_ = json::array();
  SteadyClock::time_point last_sample_{};
  bool online_ = false;
  std::uint8_t status_ = 0;
  bool jog_ = false;
  std::optional<JogSession> session_;  // the running move's (jog_), else the last one's
  bool jog_speed_ = false;
  std::uint64_t jog_generation_ = 0;  // counts presses, releases and the gateway's ends
  std::int64_t jog_value_ = 0;
  std::string jog_reason_;
  bool state_changed_ = true;
  SteadyClock::time_point last_heartbeat_{};
  SteadyClock::time_point last_refresh_{};
  Send send_;
  // The jog's goal writes not answered yet, and a stop waiting for them (stop_jog); shared with
  // their completions, which outlive the page.
  struct JogWrites {
    unsigned in_flight = 0;
    bool hold_owed = false;
  };
  std::shared_ptr<JogWrites> jog_writes_ = std::make_shared<JogWrites>();
};

Expected<std::unique_ptr<Stream>> make_servo_stream(Services& services, const PathParams& params,
                                                    const Principal& who) {
  const auto unit = servo_of(services, params);
  if (!unit) return unexpected(unit.error().body);
  return std::unique_ptr<Stream>(std::make_unique<ServoStream>(services, **unit, who));
}

// --- the bus monitor (docs/MONITOR.md) -----------------------------------------------------------

Expected<std::shared_ptr<WireMonitor>, HttpAnswer> monitor_of(const Services& services, const PathParams& params) {
  const auto name = params.get("name").value_or("");
  auto monitor = services.monitor(name);
  if (!monitor) {
    std::string buses;
    for (const auto& bus : services.config().buses) buses += (buses.empty() ? "" : ", ") + bus.name;
    return unexpected(HttpAnswer::error(404, "no bus is named " + printable(name) + " (buses: " + buses + ")"));
  }
  return monitor;
}

// The decoded frames of one bus since the page opened, batched per push period. The page sets
// its filter with {"servo": 3 | null, "requests": true, "answers": true, "errors": true}; pausing
// is the page's (it stops drawing; frames the ring overwrote meanwhile come back as `dropped`).
class MonitorStream final : public Stream {
 public:
  explicit MonitorStream(std::shared_ptr<WireMonitor> monitor)
      : bus_(monitor->bus_name()), reader_(std::move(monitor)) {}

  std::optional<std::string> flush(SteadyClock::time_point) override {
    const MonitorBatch batch = reader_.poll(kMaxRecordsPerPush, filter_);
    if (batch.frames.empty() && batch.dropped == 0) return std::nullopt;
    return to_json(bus_, batch);
  }

  void on_message(std::string_view text, const Send& send) override {
    const auto message = nlohmann::json::parse(text, nullptr, false);
    if (!message.is_object()) return send(nlohmann::json{{"error", "a filter is a JSON object"}}.dump());
    MonitorFilter filter;
    if (const auto servo = message.find("servo"); servo != message.end() && !servo->is_null()) {
      if (!servo->is_number_integer() || servo->get<int>() < 0 || servo->get<int>() > 253) {
        return send(nlohmann::json{{"error", "servo: an ID 0-253, or null for every servo"}}.dump());
      }
      filter.servo = static_cast<std::uint8_t>(servo->get<int>());
    }
    filter.requests = message.value("requests", true);
    filter.answers = message.value("answers", true);
    filter.errors = message.value("errors", true);
    filter_ = filter;
  }

 private:
  // At most this many wire records per push: a busy bus at 100 ms is far below it; a browser
  // that falls further behind is told what it missed rather than slowing anything.
  static constexpr std::size_t kMaxRecordsPerPush = 4096;
  std::string bus_;
  MonitorReader reader_;
  MonitorFilter filter_;
};

std::optional<HttpAnswer> monitor_page_missing(Services& services, const PathParams& params) {
  auto monitor = monitor_of(services, params);
  if (monitor) return std::nullopt;
  return monitor.error();
}

Expected<std::unique_ptr<Stream>> make_monitor_stream(Services& services, const PathParams& params, const Principal&) {
  auto monitor = monitor_of(services, params);
  if (!monitor) return unexpected(monitor.error().body);
  return std::unique_ptr<Stream>(std::make_unique<MonitorStream>(std::move(*monitor)));
}

// The ring's contents as a pcapng file Wireshark opens (deploy/wireshark/sms_servo.lua names the
// FF FF / D5 5D fields; Modbus RTU goes to Wireshark's own dissector).
void api_monitor_pcapng(const std::shared_ptr<ApiCall>& call) {
  const auto monitor = monitor_of(call->services, call->params);
  if (!monitor) return call->answer(monitor.error());
  const protocol::Bytes file = (*monitor)->pcapng();
  call->answer(HttpAnswer{200,
                          "application/x-pcapng",
                          std::string(file.begin(), file.end()),
                          {{"Content-Disposition", "attachment; filename=\"" + (*monitor)->bus_name() + ".pcapng\""}}});
}

constexpr Role kAnyone = Role::None;

const Route kRoutes[] = {
    // Pages (stable URLs: README "Commission a cell in the browser").
    {"GET", "/", Role::Read, RouteKind::Page, "overview.html"},
    {"GET", "/servo/{unit}", Role::Read, RouteKind::Page, "servo.html", nullptr, nullptr, true, servo_page_missing},
    {"GET", "/login", kAnyone, RouteKind::Page, "login.html"},
    {"GET", "/commission", Role::Read, RouteKind::Page, "commission.html"},
    {"GET", "/bus/{name}/monitor", Role::Read, RouteKind::Page, "monitor.html", nullptr, nullptr, true,
     monitor_page_missing},
    {"GET", "/static/{file}", kAnyone, RouteKind::Page, ""},
    // JSON.
    {"GET", "/api/session", kAnyone, RouteKind::Api, {}, api_session},
    {"POST", "/api/login", kAnyone, RouteKind::Api, {}, api_login, nullptr, false},
    {"POST", "/api/logout", Role::Read, RouteKind::Api, {}, api_logout},
    {"GET", "/api/overview", Role::Read, RouteKind::Api, {}, api_overview},
    {"GET", "/api/servo/{unit}", Role::Read, RouteKind::Api, {}, api_servo},
    {"GET", "/api/bus/{name}/monitor.pcapng", Role::Read, RouteKind::Api, {}, api_monitor_pcapng},
    {"POST", "/api/servo/{unit}/write", Role::Operate, RouteKind::Api, {}, api_servo_write},
    {"POST", "/api/estop", Role::Operate, RouteKind::Api, {}, api_estop},
    {"POST", "/api/rearm", Role::Operate, RouteKind::Api, {}, api_rearm},
    // Commissioning (engineer): a line no bus owns, through the integrator tools' code.
    {"GET", "/api/commission", Role::Read, RouteKind::Api, {}, api_commission_state},
    {"GET", "/api/commission/config.yaml", Role::Read, RouteKind::Api, {}, api_commission_config},
    {"GET", "/api/tags/{file}", Role::Read, RouteKind::Api, {}, api_tags},
    {"POST", "/api/commission/scan", Role::Engineer, RouteKind::Api, {}, api_commission_scan},
    {"POST", "/api/commission/set-id", Role::Engineer, RouteKind::Api, {}, api_commission_set_id},
    {"POST", "/api/commission/set-baud", Role::Engineer, RouteKind::Api, {}, api_commission_set_baud},
    {"POST", "/api/commission/calibrate", Role::Engineer, RouteKind::Api, {}, api_commission_calibrate},
    {"POST", "/api/commission/factory-reset", Role::Engineer, RouteKind::Api, {}, api_commission_factory_reset},
    {"POST", "/api/commission/stop-bus", Role::Engineer, RouteKind::Api, {}, api_commission_stop_bus},
    {"POST", "/api/commission/start-bus", Role::Engineer, RouteKind::Api, {}, api_commission_start_bus},
    // Live data.
    {"GET", "/ws/overview", Role::Read, RouteKind::Socket, {}, nullptr, make_overview_stream},
    {"GET", "/ws/servo/{unit}", Role::Read, RouteKind::Socket, {}, nullptr, make_servo_stream},
    {"GET", "/ws/bus/{name}/monitor", Role::Read, RouteKind::Socket, {}, nullptr, make_monitor_stream},
};

}  // namespace

HttpAnswer HttpAnswer::json(unsigned status, const nlohmann::json& body) {
  return HttpAnswer{status, "application/json", body.dump(), {}};
}

HttpAnswer HttpAnswer::error(unsigned status, std::string message) {
  return json(status, nlohmann::json{{"error", std::move(message)}});
}

HttpAnswer error_page(const HttpAnswer& refusal) {
  const auto body = nlohmann::json::parse(refusal.body, nullptr, false);
  const std::string message = body.is_object() && body.contains("error") && body["error"].is_string()
                                  ? body["error"].get<std::string>()
                                  : "HTTP " + std::to_string(refusal.status);
  // Styles from console.css only: the Content-Security-Policy allows nothing inline.
  std::string page = "<!doctype html>\n<html lang=\"en\">\n<head><meta charset=\"utf-8\"><title>sms-gateway — " +
                     std::to_string(refusal.status) +
                     "</title><link rel=\"stylesheet\" href=\"/static/console.css\"></head>\n<body>\n"
                     "<header><span class=\"brand\">sms-gateway</span><nav><a href=\"/\">Overview</a></nav></header>\n"
                     "<main>\n  <h1>Not here</h1>\n  <p id=\"message\" class=\"error\">" +
                     html_escape(message) +
                     "</p>\n  <p><a href=\"/\">Back to the overview</a></p>\n</main>\n</body>\n</html>\n";
  return HttpAnswer{refusal.status, "text/html; charset=utf-8", std::move(page), {}};
}

std::span<const Route> console_routes() { return kRoutes; }

std::string exception_text(std::uint8_t exception) {
  if (exception == 0) return "";
  // The name is the protocol's one table (protocol/modbus_pdu.h); the console adds what the
  // exception means on this gateway, for the operator reading the page.
  std::string_view meaning;
  switch (exception) {
    case 0x01: meaning = "the role may not make this request"; break;
    case 0x02: meaning = "not writable here, or not with this role"; break;
    case 0x03: meaning = "the value is out of range"; break;
    case 0x04: meaning = "motion is blocked (e-stop latched or watchdog tripped), or the servo refused"; break;
    case 0x06: meaning = "the bus queue is full, try again"; break;
    case 0x0A: meaning = "the bus is down"; break;
    case 0x0B: meaning = "the servo did not answer"; break;
    default: break;
  }
  std::string text = fmt::format("exception 0x{:02X} ({})", exception, protocol::modbus_exception_name(exception));
  if (!meaning.empty()) text += fmt::format(": {}", meaning);
  return text;
}

}  // namespace sms::gateway::console
