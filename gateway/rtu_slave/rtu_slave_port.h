#pragma once
// An upstream Modbus RTU port (docs/RTU_PANELS.md): the gateway as a Modbus RTU slave on a
// serial line whose master is a PLC or an HMI panel. Requests go to the same RequestHandler
// (the UnitRouter) the Modbus TCP listeners use, behind the port's role (the role gate of
// gateway/service/access_gate.h, as a Modbus/TCP Security certificate's), so every safety rule,
// exception and register profile is the same; what differs is the line discipline of Modbus over
// serial line v1.02 §2.5.1:
//
// - a frame ends at t3.5 of silence; a frame with a silence longer than t1.5 inside, a wrong
//   CRC, fewer than 4 or more than 256 bytes is dropped without an answer (and counted);
// - a frame for a unit the port does not serve is not answered (a serial slave that is not
//   addressed stays silent), nor is a broadcast (unit 0), whose writes are carried out on
//   every unit the port serves;
// - one request at a time, in arrival order: the next is handed to the router only once the
//   previous one is answered (a frame that arrives meanwhile waits, at most kMaxWaiting);
// - an answer starts no earlier than t3.5 after the last byte on the line;
// - the first frame after an answer, identical to it, is the adapter's echo (dropped, counted)
//   only if it ends within the port's echo window (rtu_echo_window): an FC05/FC06 answer is its
//   request byte for byte, so a master writing an unchanged value every cycle sends the same
//   frame again later, and is answered.
//
// Threading: the port has its own thread for the line (frame timing needs microseconds, which
// the io thread's other work would not give); requests are posted to the io thread, where the
// router runs, and answers come back through a Reply. A missing or lost device is retried
// every reopen_period, like a bus.
//
// The line is opened through RtuMaster::open() (libmodbus: any rate through termios2, RS-485
// mode, RTS direction control) and answers leave through libmodbus (CRC, RTS); requests are
// framed by silence here and decoded by protocol/modbus_rtu's RequestDecoder.
#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_join.h"
#include "gateway/bus/rtu_master.h"
#include "gateway/rtu_slave/rtu_slave_stats.h"
#include "gateway/service/access_gate.h"
#include "gateway/service/request_handler.h"
#include "gateway/service/role_policy.h"
#include "protocol/modbus_rtu.h"

namespace sms::gateway {

// The port's silences: t3.5 ends a frame and precedes an answer (the port's frame_gap: spec is
// 3.5 characters, 1.75 ms above 19200 bit/s); t1.5 is the longest silence inside a frame
// (3/7 of t3.5: 1.5 characters, 750 us above 19200 bit/s).
struct RtuSlaveTiming {
  std::chrono::nanoseconds t15{0};
  std::chrono::nanoseconds t35{0};
};
RtuSlaveTiming rtu_slave_timing(const SerialSettings& serial, const config::FrameGap& gap);

// How long after an answer has left the wire a frame identical to it may end and still be the
// adapter's echo (docs/RTU_PANELS.md "Echoing adapters"); nullopt with `echo: off`.
// auto: t3.5 + the answer's wire time + 1 ms. A master hears the answer's last byte, keeps t3.5
// and sends its request: the same frame again cannot end sooner, so no master's request is taken
// for an echo; an adapter hands what it heard over within a USB frame (1 ms, an FTDI with its
// latency timer at 1 ms). on: t3.5 + wire time + 50 ms, for adapters that hold short frames up
// to their latency timer (FTDI: 16 ms by default), on a loaded host.
inline constexpr std::chrono::milliseconds kEchoLatency{1};
inline constexpr std::chrono::milliseconds kLateEchoLatency{50};
std::optional<std::chrono::nanoseconds> rtu_echo_window(config::RtuEcho echo, const RtuSlaveTiming& timing,
                                                        std::chrono::nanoseconds answer_wire_time);

// The units `port` answers: its `units`, else every configured unit and the gateway unit.
std::vector<std::uint8_t> served_units(const config::Config& config, const config::RtuSlaveConfig& port);

class RtuSlavePort {
 public:
  // Frames that may wait while one request is being answered; more are dropped (a master waits
  // for each answer, so only one retrying after its own timeout gets here).
  static constexpr std::size_t kMaxWaiting = 8;

  // `router` and `policy` are used on the io thread, which `post` hands work to; both must
  // outlive the port, and the io thread must run while the port has a request in flight.
  RtuSlavePort(const config::RtuSlaveConfig& port, const config::Config& config, RequestHandler& router,
               const RolePolicy& policy, PostFn post);
  ~RtuSlavePort();  // stop(0)
  RtuSlavePort(const RtuSlavePort&) = delete;
  RtuSlavePort& operator=(const RtuSlavePort&) = delete;

  // Starts the port's thread, which opens the device (a missing one is retried, not fatal).
  void start();
  // Takes no new request; the one being answered gets up to `grace` to finish and be sent.
  void stop(std::chrono::milliseconds grace);

  // Thread-safe snapshot.
  RtuSlaveStats stats() const;
  const config::RtuSlaveConfig& settings() const { return port_; }

 private:
  struct Mailbox;
  struct Counters {
    std::atomic<bool> open{false};
    std::atomic<std::uint64_t> requests{0}, answers{0}, broadcasts{0}, crc_errors{0}, dropped_frames{0}, echoes{0},
        silent_units{0}, port_lost{0};
  };
  struct Request {
    std::uint8_t unit = 0;
    protocol::Bytes pdu;
    SteadyClock::time_point ended{};  // its last byte
  };
  struct InFlight {
    Request request;
    std::size_t waiting_for = 0;            // answers still to come (a broadcast has one per unit)
    std::optional<protocol::Bytes> answer;  // a unicast's answer, once it came
    std::uint64_t first_serial = 0;         // serials first_serial .. first_serial + count - 1
    std::size_t count = 0;
    bool orphaned = false;     // the port was lost meanwhile: no answer will be sent
    bool carried_out = false;  // a broadcast: some unit took it (a normal answer, not an exception)
  };

  void run_thread();
  void run_loop();
  bool try_open();
  void lost(const std::string& reason);
  void read_input(SteadyClock::time_point now);
  void end_of_frame();
  // Whether `frame`, the first after an answer, is its echo; forgets the answer either way.
  bool echo_of_last_answer(const protocol::Bytes& frame, SteadyClock::time_point ended);
  void accept(protocol::rtu::Adu adu, SteadyClock::time_point ended);
  void start_next();
  void collect_answers();
  void send_answer_if_due(SteadyClock::time_point now);
  std::string what() const;  // "rtu slave /dev/ttyUSB1" for logs

  const config::RtuSlaveConfig port_;
  // Who the port's requests come from, in the log lines of what they change.
  const std::shared_ptr<const std::string> origin_ =
      std::make_shared<const std::string>("an RTU master on " + port_.device);
  const RtuSlaveTiming timing_;
  RefusalCounter role_refusals_;  // before the gate that counts into it
  // On the io thread: the port's role, then the router.
  RoleGate gate_;
  const PostFn post_;
  std::vector<std::uint8_t> served_list_;
  std::array<bool, 256> served_{};
  std::vector<std::uint8_t> broadcast_units_;  // served servo and passthrough units, for unit 0
  std::shared_ptr<Mailbox> mailbox_;
  RtuMaster line_;
  Counters counters_;

  // The port thread's own state.
  protocol::rtu::RequestDecoder decoder_;
  protocol::Bytes received_;                   // the frame arriving, until t3.5 of silence
  bool receiving_ = false;                     // a frame has begun and not yet ended
  bool frame_broken_ = false;                  // a t1.5 silence inside it, or past 256 bytes
  SteadyClock::time_point last_byte_{};        // the last byte received
  SteadyClock::time_point line_busy_until_{};  // the last byte of our own answer on the wire
  protocol::Bytes last_sent_;                  // our last answer, until the frame after it (its echo?)
  SteadyClock::time_point echo_until_{};       // an echo of it ends no later than this
  bool late_echo_logged_ = false;              // auto: an identical frame just too late was reported
  bool missing_echo_logged_ = false;           // on: a frame after an answer that was not its echo, reported
  std::deque<Request> waiting_;
  std::optional<InFlight> in_flight_;
  std::uint64_t next_serial_ = 1;
  SteadyClock::time_point reopen_at_{};  // the next open attempt (none before it)
  bool open_failure_logged_ = false;
  bool ever_opened_ = false;

  // Shared with stop().
  mutable std::mutex mutex_;
  bool stopping_ = false;
  SteadyClock::time_point stop_deadline_{};
  std::thread thread_;
};

}  // namespace sms::gateway
