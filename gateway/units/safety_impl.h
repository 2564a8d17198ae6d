#pragma once
// The safety supervisor's insides (safety.h is its face and has the rules), shared by the files
// that each hold one concern: the supervisor and its thread (safety.cpp), the watchdogs
// (safety_watchdog.cpp), the e-stop latch, lent buses and the gates computed from them
// (safety_latch.cpp), the state file (safety_state.cpp), planning and sending a safe stop
// (safety_stops.cpp), the stops owed to servos it did not reach (safety_owed.cpp). Internal to
// gateway/units/.
#include <atomic>
#include <chrono>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/units/safety.h"
#include "gateway/units/state_file.h"
#include "modbus_map/motion.h"

namespace sms::gateway {

namespace asio = boost::asio;
using modbus_map::StopAction;
using Clock = std::chrono::steady_clock;

constexpr std::int64_t kNever = std::numeric_limits<std::int64_t>::min();
constexpr std::uint32_t kNoHeartbeat = 0x10000;  // above every register value

inline std::int64_t ticks(Clock::time_point when) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(when.time_since_epoch()).count();
}
inline Clock::time_point from_ticks(std::int64_t value) { return Clock::time_point(std::chrono::nanoseconds(value)); }

// One servo a safe stop covers.
struct StopTarget {
  std::uint8_t unit_id = 0;
  std::uint8_t servo_id = 0;
  const modbus_map::MotionSpec* spec = nullptr;
  modbus_map::ByteOrder order = modbus_map::ByteOrder::LowFirst;
  StopAction action = StopAction::Hold;
  std::vector<modbus_map::BusRange> context;      // what to read before a hold
  std::optional<std::uint8_t> response_level;     // as configured; empty: as read from the servo
  std::optional<std::int32_t> stop_deceleration;  // the hold's ramp; empty: the fastest (config)
};

// What a safe stop read of one target's state: its context ranges in order, and when its last
// read was answered (the hold's lead: the axis moves on from there).
struct StopReads {
  std::vector<BusResult> results;
  Clock::time_point answered{};
};

struct BusSafety {
  std::size_t index = 0;
  std::string name;
  BusEngine* engine = nullptr;
  std::shared_ptr<MotionGate> gate;
  bool packet = true;      // SYNC WRITE exists
  bool sync_read = false;  // SYNC READ exists (feetech)
  std::optional<config::WatchdogConfig> watchdog;
  config::StartAction on_start = config::StartAction::Keep;
  StopAction on_stop = StopAction::Hold;
  std::vector<StopTarget> targets;  // unit order

  std::atomic<WatchdogState> state{WatchdogState::Off};
  std::atomic<std::int64_t> last_feed{kNever};
  std::atomic<std::uint32_t> heartbeat{kNoHeartbeat};
  std::atomic<std::uint64_t> trips{0};
  std::atomic<std::int64_t> last_trip{kNever};
  std::atomic<std::uint64_t> stops{0};
  std::atomic<std::uint64_t> failed_stops{0};
  std::atomic<StopCause> last_cause{StopCause::None};
  std::atomic<std::int64_t> last_latency_us{-1};
  // Its line is lent to the console's commissioning (lend_bus): motion refused until returned.
  // Written under state_mutex_ (it is part of the gate's rule), read without it too.
  std::atomic<bool> lent{false};
};

class SafetySupervisor::Impl {
 public:
  Impl(const config::Config& config, std::vector<BusEngine*> engines, std::vector<std::shared_ptr<MotionGate>> gates);
  ~Impl();
  void start();
  void stop_for_shutdown(std::chrono::milliseconds bound);
  void feed_write(std::size_t index);
  void feed_heartbeat(std::size_t index, std::uint16_t value);
  std::optional<std::uint16_t> heartbeat_value(std::size_t index) const;
  Expected<MotionEpoch> admit_motion(std::size_t index);
  std::optional<std::string> motion_refusal(std::size_t index, std::optional<std::uint8_t> servo) const;
  void estop(const PostFn& post, std::function<void(bool)> done, std::string_view who);
  void lend_bus(std::size_t index, std::string_view who, std::function<void(bool)> done);
  void hold_servo(std::size_t index, std::uint8_t servo_id, std::string_view who, std::function<void(bool)> done);
  void return_bus(std::size_t index, std::string_view who);
  void reset_estop(std::string_view who);
  void rearm_watchdogs(std::string_view who);
  SafetyFacts facts() const;
  MotionStops motion_stops(std::size_t index) const;
  bool estop_latched() const;
  const std::string& state_file() const;
  bool any_tripped() const;
  std::size_t bus_count() const;
  std::optional<std::chrono::milliseconds> watchdog_timeout(std::size_t index) const;

 private:
  // What was read of each target's state, by target index.
  using Contexts = std::map<std::size_t, StopReads>;

  // safety.cpp: the supervisor and its thread
  PostFn safety_post();
  static PostFn run_here();
  void stop_thread();

  // safety_watchdog.cpp: the watchdogs
  void feed(BusSafety& bus);
  void reschedule();
  void check_watchdogs();

  // safety_latch.cpp: the e-stop latch, lent buses, and the gates computed from them
  void apply_gates_locked();

  // safety_state.cpp: the state file
  BusSafety* bus_named(const std::string& name) const;
  void restore();
  void restore(const SafetyStateRecord& state);
  void request_persist();
  void persist();
  void arm_persist_retry();

  // safety_stops.cpp: planning and sending a safe stop; `only`: one servo's hold (hold_servo),
  // which is not a stop of the bus (not counted, no cause).
  void run_stop(std::size_t index, StopCause cause, std::optional<StopAction> override, Clock::time_point since,
                const std::string& reason, const std::function<void(bool)>& done,
                std::optional<std::uint8_t> only = std::nullopt);
  void read_contexts(BusSafety& bus, const std::vector<std::size_t>& targets, const std::shared_ptr<Contexts>& contexts,
                     const std::function<void()>& then);
  void send_stop_frames(std::size_t index, StopCause cause, std::optional<StopAction> override, Clock::time_point since,
                        const std::string& reason, const std::function<void(bool)>& done, const Contexts& context,
                        std::optional<std::uint8_t> only);
  void submit_safely(BusSafety& bus, BusOp op, const Completion& done);

  // safety_owed.cpp: the safe stops owed to servos
  std::string owed_text() const;
  OwedStop owed_stop_for(const BusSafety& bus, const StopTarget& target, std::string_view reason) const;
  // Owes each of `targets` (indexes into bus.targets) its stop; their servo IDs, for the log.
  std::string owe_stops(BusSafety& bus, const std::vector<std::size_t>& targets, std::string_view reason);
  void restore_owed(const SafetyStateRecord& state);

  asio::io_context io_;
  asio::executor_work_guard<asio::io_context::executor_type> work_ = asio::make_work_guard(io_);
  asio::steady_timer timer_;
  std::thread thread_;
  std::vector<std::unique_ptr<BusSafety>> buses_;
  // Every change of the latch, a watchdog's tripped state or shutting_down_, and the gates
  // computed from them, happen under this lock (apply_gates_locked).
  mutable std::mutex state_mutex_;
  std::atomic<bool> estop_latched_{false};
  bool shutting_down_ = false;
  std::atomic<std::uint64_t> estops_{0};
  std::atomic<bool> shutdown_done_{false};
  std::string state_path_;  // empty: not kept
  std::mutex persist_mutex_;
  std::atomic<bool> persist_queued_{false};  // request_persist(): a write is posted and has not begun
  std::atomic<bool> not_persisted_{false};   // the last write failed
  mutable std::mutex problem_mutex_;
  std::string persist_problem_;  // guarded by problem_mutex_: why the last write failed
  static constexpr std::chrono::seconds kPersistRetry{1};
  asio::steady_timer retry_timer_{io_};
  bool retry_armed_ = false;  // safety thread only
};

}  // namespace sms::gateway
