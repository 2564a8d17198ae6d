#include "gateway/rtu_slave/rtu_slave_port.h"

#include <poll.h>
#include <pthread.h>
#include <sys/prctl.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <utility>

#include <spdlog/spdlog.h>

#include "gateway/bus/wakeup.h"
#include "gateway/service/modbus_request.h"
#include "protocol/hex_text.h"
#include "protocol/modbus_pdu.h"

namespace sms::gateway {

using protocol::Bytes;
namespace fc = protocol::function_code;

namespace {

// Broadcast forms (Modbus over serial line v1.02 §2.1: only writes): a read answers data, which a
// broadcast never gets back; FC23 reads too.
bool broadcastable(std::uint8_t function) {
  return function == fc::kWriteSingleCoil || function == fc::kWriteSingleRegister ||
         function == fc::kWriteMultipleCoils || function == fc::kWriteMultipleRegisters;
}

std::string line_text(const config::RtuSlaveConfig& port) {
  const char parity = port.parity == config::Parity::Even ? 'E' : port.parity == config::Parity::Odd ? 'O' : 'N';
  return std::to_string(port.baud) + " bit/s 8" + parity + std::to_string(port.stop_bits);
}

std::string units_text(const std::vector<std::uint8_t>& units) {
  std::string text;
  for (const auto unit : units) text += (text.empty() ? "" : ",") + std::to_string(unit);
  return text;
}

}  // namespace

RtuSlaveTiming rtu_slave_timing(const SerialSettings& serial, const config::FrameGap& gap) {
  const auto t35 = rtu_frame_gap(serial, gap);
  return RtuSlaveTiming{t35 * 3 / 7, t35};
}

std::optional<std::chrono::nanoseconds> rtu_echo_window(config::RtuEcho echo, const RtuSlaveTiming& timing,
                                                        std::chrono::nanoseconds answer_wire_time) {
  switch (echo) {
    case config::RtuEcho::Auto: return timing.t35 + answer_wire_time + kEchoLatency;
    case config::RtuEcho::On: return timing.t35 + answer_wire_time + kLateEchoLatency;
    case config::RtuEcho::Off: return std::nullopt;
  }
  return std::nullopt;
}

std::vector<std::uint8_t> served_units(const config::Config& config, const config::RtuSlaveConfig& port) {
  if (!port.units.empty()) return port.units;
  std::vector<std::uint8_t> units;
  for (const auto& servo : config.servos) units.push_back(servo.unit_id);
  units.push_back(config.modbus_tcp.gateway_unit_id);
  std::sort(units.begin(), units.end());
  return units;
}

// Where the router's answers land: on the io thread, for the port thread to take.
struct RtuSlavePort::Mailbox final : Reply::Target {
  void deliver(std::uint64_t request_serial, Bytes response_pdu) override {
    {
      std::lock_guard lock(mutex);
      answers.emplace_back(request_serial, std::move(response_pdu));
    }
    wake.notify();
  }

  std::mutex mutex;
  std::vector<std::pair<std::uint64_t, Bytes>> answers;
  Wakeup wake;
};

RtuSlavePort::RtuSlavePort(const config::RtuSlaveConfig& port, const config::Config& config, RequestHandler& router,
                           const RolePolicy& policy, PostFn post)
    : port_(port),
      timing_(
          rtu_slave_timing(SerialSettings{port.device, port.baud, port.parity, port.stop_bits}, port.line.frame_gap)),
      gate_(policy, port.role, what(), &role_refusals_, router),
      post_(std::move(post)),
      mailbox_(std::make_shared<Mailbox>()),
      line_(RtuLineSettings{SerialSettings{port.device, port.baud, port.parity, port.stop_bits}, port.line}) {
  served_list_ = served_units(config, port);
  for (const auto unit : served_list_) {
    served_[unit] = true;
    if (unit != config.modbus_tcp.gateway_unit_id) broadcast_units_.push_back(unit);
  }
}

RtuSlavePort::~RtuSlavePort() { stop(std::chrono::milliseconds{0}); }

void RtuSlavePort::start() {
  if (thread_.joinable()) throw std::logic_error(what() + ": start() called twice");
  thread_ = std::thread([this] { run_thread(); });
}

void RtuSlavePort::stop(std::chrono::milliseconds grace) {
  {
    std::lock_guard lock(mutex_);
    if (!stopping_) {
      stopping_ = true;
      stop_deadline_ = SteadyClock::now() + grace;
    }
  }
  mailbox_->wake.notify();
  if (thread_.joinable()) thread_.join();
}

RtuSlaveStats RtuSlavePort::stats() const {
  RtuSlaveStats stats;
  stats.device = port_.device;
  stats.open = counters_.open.load();
  stats.requests = counters_.requests.load();
  stats.answers = counters_.answers.load();
  stats.broadcasts = counters_.broadcasts.load();
  stats.crc_errors = counters_.crc_errors.load();
  stats.dropped_frames = counters_.dropped_frames.load();
  stats.echoes = counters_.echoes.load();
  stats.silent_units = counters_.silent_units.load();
  stats.role_refusals = role_refusals_.total();
  stats.port_lost = counters_.port_lost.load();
  return stats;
}

std::string RtuSlavePort::what() const { return "rtu slave " + port_.device; }

void RtuSlavePort::run_thread() {
  ::pthread_setname_np(::pthread_self(), "rtu slave");
  // t1.5 and t3.5 are hundreds of microseconds above 19200 bit/s: the default 50 us timer
  // slack would be a fifth of them.
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
  try {
    run_loop();
  } catch (const std::exception& error) {
    spdlog::critical("{}: internal error on the port thread: {}; the port stops", what(), error.what());
  }
  line_.close();
  counters_.open.store(false);
}

void RtuSlavePort::run_loop() {
  for (;;) {
    bool stopping = false;
    SteadyClock::time_point stop_deadline;
    {
      std::lock_guard lock(mutex_);
      stopping = stopping_;
      stop_deadline = stop_deadline_;
    }
    collect_answers();
    if (stopping) {
      waiting_.clear();  // not started: no answer was promised
      if (!in_flight_ || SteadyClock::now() >= stop_deadline) return;
    }
    if (!line_.is_open()) {
      // Like a bus: a missing or lost device is tried again once per reopen period, so a device
      // that fails right after each open cannot make the port spin.
      if (SteadyClock::now() < reopen_at_ || !try_open()) {
        if (SteadyClock::now() >= reopen_at_) reopen_at_ = SteadyClock::now() + port_.reopen_period;
        mailbox_->wake.wait(stopping ? std::min(reopen_at_, stop_deadline) : reopen_at_);  // or an answer, stop()
        continue;
      }
    }
    if (!stopping) start_next();

    // Sleep until a byte arrives, an answer comes, the frame ends or the answer is due.
    std::optional<SteadyClock::time_point> deadline;
    const auto earliest = [&](SteadyClock::time_point at) { deadline = deadline ? std::min(*deadline, at) : at; };
    if (receiving_) earliest(last_byte_ + timing_.t35);
    if (in_flight_ && in_flight_->answer) earliest(std::max(last_byte_ + timing_.t35, line_busy_until_));
    if (stopping) earliest(stop_deadline);
    std::array<pollfd, 2> fds{pollfd{line_.native_handle(), POLLIN, 0},
                              pollfd{mailbox_->wake.native_handle(), POLLIN, 0}};
    timespec timeout{};
    timespec* timeout_pointer = nullptr;
    if (deadline) {
      const auto left = std::max(std::chrono::nanoseconds{0}, *deadline - SteadyClock::now());
      timeout.tv_sec = static_cast<time_t>(left.count() / 1'000'000'000);
      timeout.tv_nsec = static_cast<long>(left.count() % 1'000'000'000);
      timeout_pointer = &timeout;
    }
    const int ready = ::ppoll(fds.data(), fds.size(), timeout_pointer, nullptr);
    if (ready < 0 && errno != EINTR) throw std::runtime_error(std::string("ppoll: ") + std::strerror(errno));
    const auto now = SteadyClock::now();
    if (ready > 0 && fds[0].revents != 0) read_input(now);
    if (ready > 0 && fds[1].revents != 0) mailbox_->wake.wait(SteadyClock::time_point{});  // consume
    if (receiving_ && now >= last_byte_ + timing_.t35) end_of_frame();
    collect_answers();
    send_answer_if_due(SteadyClock::now());
  }
}

bool RtuSlavePort::try_open() {
  const auto opened = line_.open();
  if (!opened) {
    if (!open_failure_logged_) {
      spdlog::error("{}: {}; retrying every {} ms", what(), opened.error(), port_.reopen_period.count());
      open_failure_logged_ = true;
    } else {
      spdlog::debug("{}: still cannot open: {}", what(), opened.error());
    }
    return false;
  }
  open_failure_logged_ = false;
  spdlog::info("{}: {} at {}, t3.5 {} us, answering units {} with role {}", what(), ever_opened_ ? "reopened" : "open",
               line_text(port_), std::chrono::duration_cast<std::chrono::microseconds>(timing_.t35).count(),
               units_text(served_list_), config::to_string(port_.role));
  ever_opened_ = true;
  counters_.open.store(true);
  received_.clear();
  receiving_ = false;
  frame_broken_ = false;
  last_sent_.clear();
  last_byte_ = SteadyClock::now();
  return true;
}

void RtuSlavePort::lost(const std::string& reason) {
  spdlog::error("{}: {} — port lost; reopening every {} ms", what(), reason, port_.reopen_period.count());
  counters_.port_lost.fetch_add(1, std::memory_order_relaxed);
  counters_.open.store(false);
  line_.close();
  reopen_at_ = SteadyClock::now() + port_.reopen_period;
  received_.clear();
  receiving_ = false;
  frame_broken_ = false;
  last_sent_.clear();
  // As for a TCP client that goes away: the request on its way still completes (a write is
  // never dropped half-way) and its answer, having no line to go to, is discarded; the requests
  // waiting behind it are not started (a stale move must not run when the adapter comes back).
  if (in_flight_) in_flight_->orphaned = true;
  waiting_.clear();
}

void RtuSlavePort::read_input(SteadyClock::time_point now) {
  std::array<std::uint8_t, 512> buffer{};
  bool first_chunk = true;
  for (;;) {
    const ssize_t got = ::read(line_.native_handle(), buffer.data(), buffer.size());
    if (got < 0 && errno == EINTR) continue;
    if (got < 0 && errno == EAGAIN) break;
    if (got <= 0) {
      lost(got == 0 ? std::string("end of file (the device went away)") : "read: " + std::string(std::strerror(errno)));
      return;
    }
    const auto count = static_cast<std::size_t>(got);
    if (receiving_ && first_chunk) {
      // The silence before this chunk: the time since the last one less the chunk's own wire time
      // (an adapter hands bytes over in bursts, each after its last byte arrived).
      const auto silence = (now - last_byte_) - wire_time(line_.settings().serial, count);
      if (silence > timing_.t15) frame_broken_ = true;
    }
    if (received_.size() + count > protocol::rtu::kMaxAduSize) {
      frame_broken_ = true;  // still timed to its end, but its bytes are not kept
    } else {
      received_.insert(received_.end(), buffer.begin(), buffer.begin() + got);
    }
    receiving_ = true;
    first_chunk = false;
  }
  if (!first_chunk) last_byte_ = now;
}

void RtuSlavePort::end_of_frame() {
  Bytes frame = std::move(received_);
  received_.clear();
  receiving_ = false;
  const bool broken = frame_broken_;
  frame_broken_ = false;
  const auto ended = last_byte_;
  if (echo_of_last_answer(frame, ended)) {  // before `broken`: an adapter may hand its echo over in bursts
    counters_.echoes.fetch_add(1, std::memory_order_relaxed);
    spdlog::trace("{}: the adapter's echo of the answer ({} bytes) dropped", what(), frame.size());
    return;
  }
  if (broken) {
    counters_.dropped_frames.fetch_add(1, std::memory_order_relaxed);
    spdlog::debug("{}: frame of {} bytes dropped: a silence longer than t1.5 inside it, or longer than {} bytes",
                  what(), frame.size(), protocol::rtu::kMaxAduSize);
    return;
  }
  decoder_.reset();
  decoder_.feed(frame);
  auto event = decoder_.end_of_frame();
  if (!event) {
    counters_.dropped_frames.fetch_add(1, std::memory_order_relaxed);
    spdlog::debug("{}: {} byte(s) of noise dropped: {}", what(), frame.size(), protocol::hex_bytes(frame));
    return;
  }
  if (event->kind == protocol::rtu::RequestDecoder::Event::Kind::CrcError) {
    counters_.crc_errors.fetch_add(1, std::memory_order_relaxed);
    spdlog::debug("{}: frame with a wrong CRC dropped: {}", what(), protocol::hex_bytes(frame));
    return;
  }
  accept(std::move(event->adu), ended);
}

bool RtuSlavePort::echo_of_last_answer(const Bytes& frame, SteadyClock::time_point ended) {
  if (last_sent_.empty()) return false;
  // Only the first frame after an answer can be its echo: the adapter hands it back before
  // anything a master sends after hearing the answer.
  const Bytes answer = std::exchange(last_sent_, Bytes{});
  const bool identical = frame == answer;
  if (identical && ended <= echo_until_) return true;
  const auto after_ms =
      std::chrono::duration_cast<std::chrono::milliseconds>(ended - line_busy_until_).count();  // after the answer
  if (port_.echo == config::RtuEcho::Auto && identical && !late_echo_logged_ &&
      ended - line_busy_until_ <= kLateEchoLatency) {
    // A master repeating the frame this soon, or an adapter echoing late (answered as a request
    // each time, so the late echo of the new answer comes back too): said once per port.
    late_echo_logged_ = true;
    spdlog::warn(
        "{}: a frame identical to the answer just sent ended {} ms after it, too late to be the adapter's echo "
        "with `echo: auto`; answered as a request. If this adapter hands back what the port sends and is slow "
        "to (an FTDI latency timer, 16 ms by default), set `echo: on` on this port or the timer to 1 ms",
        what(), after_ms);
  }
  if (port_.echo == config::RtuEcho::On && !missing_echo_logged_) {
    missing_echo_logged_ = true;
    spdlog::warn(
        "{}: `echo: on`, but the frame after an answer was not its echo ({} bytes, {}, ending {} ms after the "
        "answer); if this adapter does not hand back what the port sends, set `echo: auto` or `echo: off`",
        what(), frame.size(), identical ? "identical but late" : "a different frame", after_ms);
  }
  return false;
}

void RtuSlavePort::accept(protocol::rtu::Adu adu, SteadyClock::time_point ended) {
  const bool broadcast = adu.slave == 0;
  if (!broadcast && !served_[adu.slave]) {
    // Another slave's request (or its answer) on a shared line, or a unit this port does not
    // serve: a serial slave that is not addressed stays silent.
    counters_.silent_units.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  if (broadcast && (adu.pdu.empty() || !broadcastable(adu.pdu[0]))) {
    counters_.dropped_frames.fetch_add(1, std::memory_order_relaxed);
    spdlog::debug("{}: broadcast FC{:02X} dropped: only writes are broadcast", what(),
                  adu.pdu.empty() ? 0 : adu.pdu[0]);
    return;
  }
  if (waiting_.size() >= kMaxWaiting) {
    counters_.dropped_frames.fetch_add(1, std::memory_order_relaxed);
    spdlog::warn(
        "{}: request for unit {} dropped: {} requests already wait behind the one being answered (a "
        "master that does not wait for its answers?)",
        what(), adu.slave, kMaxWaiting);
    return;
  }
  counters_.requests.fetch_add(1, std::memory_order_relaxed);
  waiting_.push_back(Request{adu.slave, std::move(adu.pdu), ended});
}

void RtuSlavePort::start_next() {
  if (in_flight_ || waiting_.empty()) return;
  InFlight flight;
  flight.request = std::move(waiting_.front());
  waiting_.pop_front();
  const bool broadcast = flight.request.unit == 0;
  const std::vector<std::uint8_t> units = broadcast ? broadcast_units_ : std::vector<std::uint8_t>{flight.request.unit};
  flight.first_serial = next_serial_;
  flight.count = units.size();
  flight.waiting_for = units.size();
  next_serial_ += units.size();
  in_flight_ = std::move(flight);
  if (units.empty()) {  // a broadcast on a port that serves only the gateway unit
    in_flight_.reset();
    return;
  }
  // One request at a time: a broadcast's units are handed over together (each bus keeps their
  // order) and the port waits for all of them before the next request.
  auto pdu = std::make_shared<const Bytes>(in_flight_->request.pdu);
  for (std::size_t i = 0; i < units.size(); ++i) {
    Reply reply(mailbox_, in_flight_->first_serial + i, origin_);
    post_([this, unit = units[i], pdu, reply] { gate_.handle(unit, *pdu, reply); });
  }
}

void RtuSlavePort::collect_answers() {
  std::vector<std::pair<std::uint64_t, Bytes>> answers;
  {
    std::lock_guard lock(mailbox_->mutex);
    answers.swap(mailbox_->answers);
  }
  for (auto& [serial, pdu] : answers) {
    if (!in_flight_ || serial < in_flight_->first_serial || serial >= in_flight_->first_serial + in_flight_->count) {
      continue;  // a second send() for a request already answered
    }
    if (in_flight_->request.unit != 0) {
      if (in_flight_->answer) continue;
      in_flight_->answer = std::move(pdu);
    } else if (!pdu.empty() && (pdu[0] & 0x80) == 0) {
      in_flight_->carried_out = true;
    }
    if (in_flight_->waiting_for > 0) --in_flight_->waiting_for;
  }
  // A broadcast is never answered; an orphaned request's answer has nowhere to go. It is counted
  // once its units have all said: carried out when one of them took it (a tripped watchdog or the
  // e-stop refuses it on every unit: not counted; the log says why).
  if (in_flight_ && in_flight_->waiting_for == 0 && (in_flight_->request.unit == 0 || in_flight_->orphaned)) {
    if (in_flight_->request.unit == 0 && in_flight_->carried_out) {
      counters_.broadcasts.fetch_add(1, std::memory_order_relaxed);
    }
    in_flight_.reset();
  }
}

void RtuSlavePort::send_answer_if_due(SteadyClock::time_point now) {
  if (!in_flight_ || !in_flight_->answer || !line_.is_open()) return;
  // Not while a frame is arriving (half duplex), and t3.5 after the last byte on the line.
  if (receiving_ || now < last_byte_ + timing_.t35 || now < line_busy_until_) return;
  const Bytes& pdu = *in_flight_->answer;
  if (pdu.empty()) {  // Reply::finish_without_answer()
    in_flight_.reset();
    return;
  }
  const std::uint8_t unit = in_flight_->request.unit;
  if (const auto sent = line_.send_frame(unit, pdu); !sent) {
    in_flight_.reset();
    lost(sent.error());
    return;
  }
  counters_.answers.fetch_add(1, std::memory_order_relaxed);
  Bytes sent = protocol::rtu::frame(unit, pdu);
  const auto on_wire = wire_time(line_.settings().serial, sent.size());
  line_busy_until_ = SteadyClock::now() + on_wire;
  if (const auto window = rtu_echo_window(port_.echo, timing_, on_wire)) {
    last_sent_ = std::move(sent);
    echo_until_ = line_busy_until_ + *window;
  }
  in_flight_.reset();
}

}  // namespace sms::gateway
