#include "gateway/bus/rtu_bus_engine.h"

#include <fcntl.h>
#include <modbus/modbus.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/prctl.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <bitset>
#include <array>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <variant>

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include "gateway/bus/discovery.h"
#include "gateway/bus/job_queue.h"
#include "gateway/bus/poll_scheduler.h"
#include "gateway/bus/serial_port_termios2.h"
#include "modbus_map/tables.h"
#include "protocol/modbus_pdu.h"
#include "protocol/modbus_rtu.h"

namespace sms::gateway {

using namespace std::chrono_literals;
using protocol::Bytes;

// ==== rates and timing ========================================================================

namespace {

// The rates libmodbus 3.1.6 maps to Bxxx constants on Linux (_get_termios_speed in
// modbus-rtu.c); any other rate becomes B9600 there.
constexpr std::array<std::uint32_t, 23> kLibmodbusRates{
    110,    300,    600,    1200,   2400,    4800,    9600,    19200,   38400,   57600,   115200,  230400,
    460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2500000, 3000000, 3500000, 4000000};

constexpr std::uint32_t kFixedGapAbove = 19200;
constexpr auto kFixedFrameGap = 1750us;

}  // namespace

bool libmodbus_sets_rate(std::uint32_t baud) {
  return std::find(kLibmodbusRates.begin(), kLibmodbusRates.end(), baud) != kLibmodbusRates.end();
}

std::chrono::nanoseconds rtu_frame_gap(const SerialSettings& serial, const config::FrameGap& gap) {
  const auto three_and_a_half_characters = wire_time(serial, 7) / 2;
  switch (gap.kind) {
    case config::FrameGap::Kind::Spec:
      return serial.baud > kFixedGapAbove ? std::chrono::nanoseconds{kFixedFrameGap} : three_and_a_half_characters;
    case config::FrameGap::Kind::Characters:
      return three_and_a_half_characters;
    case config::FrameGap::Kind::Fixed:
      return gap.fixed;
  }
  return three_and_a_half_characters;
}

std::string_view to_string(RtuOutcome outcome) {
  switch (outcome) {
    case RtuOutcome::Reply: return "reply";
    case RtuOutcome::Sent: return "sent";
    case RtuOutcome::Timeout: return "timeout";
    case RtuOutcome::Corrupt: return "corrupt reply";
    case RtuOutcome::WrongSlave: return "reply from another slave";
    case RtuOutcome::PortError: return "port error";
  }
  return "?";
}

// ==== RtuMaster ===============================================================================

namespace {

// Function codes whose confirmation length libmodbus 3.1.6 computes (modbus.c,
// compute_meta_length_after_function / compute_data_length_after_meta); exception answers
// (code | 0x80) it always sizes right. Other codes are framed by silence.
constexpr std::array<std::uint8_t, 12> kLibmodbusSizedFunctions{0x01, 0x02, 0x03, 0x04, 0x05, 0x06,
                                                                0x07, 0x0F, 0x10, 0x11, 0x16, 0x17};

bool libmodbus_sizes(std::uint8_t function) {
  return std::find(kLibmodbusSizedFunctions.begin(), kLibmodbusSizedFunctions.end(), function) !=
         kLibmodbusSizedFunctions.end();
}

char parity_letter(config::Parity parity) {
  switch (parity) {
    case config::Parity::Even: return 'E';
    case config::Parity::Odd: return 'O';
    case config::Parity::None: break;
  }
  return 'N';
}

std::string open_hint(int error) {
  switch (error) {
    case ENOENT:
      return " — the device does not exist: is the adapter plugged in, and is the device path right? "
             "(ls -l /dev/serial/by-id/ lists adapters by a name that survives re-plugging)";
    case EACCES:
    case EPERM:
      return " — no permission: add the user to the group owning the device (usually `dialout`)";
    case EBUSY:
      return " — another program holds the device (fuser -v DEVICE shows which)";
    case ENOTTY:
    case EINVAL:
      return " — this is not a serial device, or its driver refuses these line settings";
    default:
      return "";
  }
}

// libmodbus takes seconds and microseconds, microseconds below 1 000 000, not both zero.
void split_timeout(std::chrono::nanoseconds timeout, std::uint32_t& seconds, std::uint32_t& micros) {
  const auto total = std::max<std::int64_t>(std::chrono::ceil<std::chrono::microseconds>(timeout).count(), 1);
  seconds = static_cast<std::uint32_t>(total / 1'000'000);
  micros = static_cast<std::uint32_t>(total % 1'000'000);
}

int poll_ms(std::chrono::nanoseconds timeout) {
  if (timeout <= 0ns) return 0;
  return static_cast<int>(std::min<std::int64_t>(std::chrono::ceil<std::chrono::milliseconds>(timeout).count(), 60'000));
}

std::string hex(std::span<const std::uint8_t> bytes) {
  std::string text;
  for (const auto byte : bytes) text += fmt::format("{}{:02X}", text.empty() ? "" : " ", byte);
  return text;
}

}  // namespace

struct RtuMaster::Line {
  modbus_t* context = nullptr;
  SteadyClock::time_point quiet_since{};  // when the line last fell silent (a frame ended)
};

RtuMaster::RtuMaster(RtuLineSettings settings) : settings_(std::move(settings)), line_(std::make_unique<Line>()) {}

RtuMaster::~RtuMaster() { close(); }

bool RtuMaster::is_open() const { return line_->context != nullptr; }

void RtuMaster::close() {
  if (line_->context == nullptr) return;
  // Give up exclusivity first: it outlives our descriptor while anyone else holds the tty (a
  // pty's other users), and a reopen would then fail with EBUSY for non-root users.
  (void)ioctl(modbus_get_socket(line_->context), TIOCNXCL);
  modbus_close(line_->context);
  modbus_free(line_->context);
  line_->context = nullptr;
}

Expected<Ok> RtuMaster::open() {
  close();
  const SerialSettings& serial = settings_.serial;
  const std::string where = serial.device + " at " + std::to_string(serial.baud) + " bit/s";
  modbus_t* context =
      modbus_new_rtu(serial.device.c_str(), static_cast<int>(serial.baud), parity_letter(serial.parity), 8,
                     serial.stop_bits == 2 ? 2 : 1);
  if (context == nullptr) return unexpected("cannot set up a Modbus RTU line on " + where + ": " + modbus_strerror(errno));
  if (modbus_connect(context) != 0) {
    const int error = errno;
    modbus_free(context);
    return unexpected("cannot open " + serial.device + ": " + std::strerror(error) + open_hint(error));
  }
  const auto fail = [&](const std::string& message) -> Expected<Ok> {
    modbus_close(context);
    modbus_free(context);
    return unexpected(message);
  };
  const int fd = modbus_get_socket(context);
  // One program per bus: a second master on the same line garbles both. Some drivers refuse
  // it; that is not worth failing for.
  (void)ioctl(fd, TIOCEXCL);
  // Every rate through termios2: libmodbus 3.1.6 would have set 9600 for 256000, 128000,
  // 56000, 14400 ... without a word (see the header).
  if (const int error = detail::configure_raw_line(fd, serial.baud, serial.parity, serial.stop_bits);
      error != 0) {
    return fail("cannot set " + where + ": " + std::strerror(error) + open_hint(error));
  }
  const config::ModbusRtuOptions& options = settings_.options;
  if (options.rs485 && modbus_rtu_set_serial_mode(context, MODBUS_RTU_RS485) != 0) {
    return fail("cannot switch " + serial.device + " to RS-485 mode (TIOCSRS485): " + modbus_strerror(errno) +
                " — this adapter has no kernel RS-485 mode: set `rs485: false` (USB RS-485 adapters switch "
                "direction by themselves) or use `rts: up|down` for adapters that need RTS");
  }
  if (options.rts != config::RtsMode::None) {
    const int mode = options.rts == config::RtsMode::Up ? MODBUS_RTU_RTS_UP : MODBUS_RTU_RTS_DOWN;
    if (modbus_rtu_set_rts(context, mode) != 0) {
      return fail("cannot use RTS direction control on " + serial.device + ": " + modbus_strerror(errno));
    }
    if (options.rts_delay && modbus_rtu_set_rts_delay(context, static_cast<int>(options.rts_delay->count())) != 0) {
      return fail("cannot set the RTS delay on " + serial.device + ": " + modbus_strerror(errno));
    }
  }
  std::uint32_t seconds = 0;
  std::uint32_t micros = 0;
  split_timeout(options.byte_timeout, seconds, micros);
  modbus_set_byte_timeout(context, seconds, micros);
  modbus_set_error_recovery(context, MODBUS_ERROR_RECOVERY_NONE);
  std::uint32_t actual = 0;
  if (detail::read_line_speed(fd, actual) == 0 && actual != serial.baud) {
    spdlog::warn("{}: the driver runs the line at {} bit/s instead of {}", serial.device, actual, serial.baud);
  }
  line_->context = context;
  line_->quiet_since = SteadyClock::now();
  return Ok{};
}

void RtuMaster::wait_for_frame_gap() {
  const auto ready = line_->quiet_since + rtu_frame_gap(settings_.serial, settings_.options.frame_gap);
  const auto now = SteadyClock::now();
  if (ready > now) std::this_thread::sleep_for(ready - now);
}

RtuExchange RtuMaster::transact(std::uint8_t slave, std::span<const std::uint8_t> pdu,
                                std::chrono::nanoseconds reply_timeout) {
  if (!is_open()) return {RtuOutcome::PortError, {}, settings_.serial.device + " is not open"};
  if (pdu.empty() || pdu.size() > protocol::rtu::kMaxAduSize - 3) {
    throw std::invalid_argument("RtuMaster::transact: a PDU is 1 to 253 bytes, not " + std::to_string(pdu.size()));
  }
  modbus_t* context = line_->context;
  wait_for_frame_gap();
  modbus_flush(context);  // late replies and noise would otherwise be read as this answer
  modbus_set_slave(context, slave);
  Bytes request;
  request.reserve(pdu.size() + 1);
  request.push_back(slave);
  request.insert(request.end(), pdu.begin(), pdu.end());
  // The reply timeout counts from when the request has left the wire (write() returns at once).
  const auto response_timeout = wire_time(request.size() + 2) + reply_timeout;
  std::uint32_t seconds = 0;
  std::uint32_t micros = 0;
  split_timeout(response_timeout, seconds, micros);
  modbus_set_response_timeout(context, seconds, micros);
  if (modbus_send_raw_request(context, request.data(), static_cast<int>(request.size())) < 0) {
    const int error = errno;
    return {RtuOutcome::PortError, {}, "write to " + settings_.serial.device + ": " + modbus_strerror(error)};
  }
  if (!libmodbus_sizes(pdu[0])) return receive_until_silence(slave, response_timeout);

  std::array<std::uint8_t, MODBUS_RTU_MAX_ADU_LENGTH> answer{};
  const int received = modbus_receive_confirmation(context, answer.data());
  const int error = errno;
  line_->quiet_since = SteadyClock::now();
  if (received < 0) {
    switch (error) {
      case ETIMEDOUT:
        return {RtuOutcome::Timeout, {}, fmt::format("no answer from slave {} within {} us", slave,
                                                     std::chrono::duration_cast<std::chrono::microseconds>(
                                                         response_timeout).count())};
      case EMBBADCRC:
      case EMBBADDATA:
      case EMBMDATA:
        return {RtuOutcome::Corrupt, {}, fmt::format("answer from slave {}: {}", slave, modbus_strerror(error))};
      case EMBBADSLAVE:
        return {RtuOutcome::WrongSlave, {}, fmt::format("asked slave {}: {}", slave, modbus_strerror(error))};
      default:
        return {RtuOutcome::PortError, {}, "read from " + settings_.serial.device + ": " + modbus_strerror(error)};
    }
  }
  // libmodbus 3.1.6 returns 0 for a frame addressed from another slave (filtered before its CRC).
  if (received < 4 || answer[0] != slave) {
    RtuExchange exchange{RtuOutcome::WrongSlave, {}, fmt::format("asked slave {}, a frame from another slave came", slave)};
    if (received >= 1) exchange.other_slave = answer[0];
    return exchange;
  }
  return {RtuOutcome::Reply, Bytes(answer.begin() + 1, answer.begin() + received - 2), {}};
}

RtuExchange RtuMaster::receive_until_silence(std::uint8_t slave, std::chrono::nanoseconds first_byte_timeout) {
  // Without a length rule for the function, the answer is whatever arrives until the line
  // stays silent for the byte timeout (3.5 characters would be the letter of the standard; USB
  // adapters deliver in bursts with larger gaps).
  const int fd = modbus_get_socket(line_->context);
  Bytes frame;
  std::array<std::uint8_t, protocol::rtu::kMaxAduSize> buffer{};
  auto wait = first_byte_timeout;
  for (;;) {
    pollfd descriptor{fd, POLLIN, 0};
    const int ready = ::poll(&descriptor, 1, poll_ms(wait));
    if (ready < 0) {
      if (errno == EINTR) continue;
      return {RtuOutcome::PortError, {}, "poll " + settings_.serial.device + ": " + std::strerror(errno)};
    }
    if (ready == 0) break;
    const ssize_t got = ::read(fd, buffer.data(), buffer.size());
    if (got < 0 && (errno == EAGAIN || errno == EINTR)) continue;
    if (got <= 0) {
      return {RtuOutcome::PortError, {}, "read from " + settings_.serial.device + ": " +
                                             (got == 0 ? std::string("end of file") : std::strerror(errno))};
    }
    frame.insert(frame.end(), buffer.begin(), buffer.begin() + got);
    if (frame.size() > protocol::rtu::kMaxAduSize) {
      line_->quiet_since = SteadyClock::now();
      return {RtuOutcome::Corrupt, {}, fmt::format("answer from slave {} longer than 256 bytes", slave)};
    }
    wait = settings_.options.byte_timeout;
  }
  line_->quiet_since = SteadyClock::now();
  if (frame.empty()) return {RtuOutcome::Timeout, {}, fmt::format("no answer from slave {}", slave)};
  if (frame.size() < protocol::rtu::kMinAduSize ||
      protocol::rtu::crc16(std::span(frame).first(frame.size() - 2)) !=
          static_cast<std::uint16_t>(frame[frame.size() - 2] | frame[frame.size() - 1] << 8)) {
    return {RtuOutcome::Corrupt, {}, fmt::format("answer from slave {} with a wrong CRC: {}", slave, hex(frame))};
  }
  if (frame[0] != slave) {
    return {RtuOutcome::WrongSlave, {}, fmt::format("asked slave {}, slave {} answered", slave, frame[0]), frame[0]};
  }
  return {RtuOutcome::Reply, Bytes(frame.begin() + 1, frame.end() - 2), {}};
}

RtuExchange RtuMaster::send_only(std::uint8_t slave, std::span<const std::uint8_t> pdu,
                                 std::chrono::nanoseconds turnaround) {
  if (!is_open()) return {RtuOutcome::PortError, {}, settings_.serial.device + " is not open"};
  if (pdu.empty() || pdu.size() > protocol::rtu::kMaxAduSize - 3) {
    throw std::invalid_argument("RtuMaster::send_only: a PDU is 1 to 253 bytes, not " + std::to_string(pdu.size()));
  }
  modbus_t* context = line_->context;
  wait_for_frame_gap();
  modbus_flush(context);
  modbus_set_slave(context, slave);
  Bytes request;
  request.push_back(slave);
  request.insert(request.end(), pdu.begin(), pdu.end());
  if (modbus_send_raw_request(context, request.data(), static_cast<int>(request.size())) < 0) {
    return {RtuOutcome::PortError, {}, "write to " + settings_.serial.device + ": " + modbus_strerror(errno)};
  }
  const auto on_wire = wire_time(request.size() + 2);
  std::this_thread::sleep_for(on_wire + turnaround);
  line_->quiet_since = SteadyClock::now();
  return {RtuOutcome::Sent, {}, {}};
}

// ==== RtuBusEngine ============================================================================

namespace {

namespace fc = protocol::function_code;

constexpr std::uint8_t kBroadcastSlave = 0;
constexpr std::uint8_t kMaxSlave = 247;
constexpr std::uint16_t kMaxReadRegisters = protocol::modbus_limits::kReadRegisters;
constexpr std::uint16_t kMaxWriteRegisters = protocol::modbus_limits::kWriteRegisters;
constexpr std::size_t kMaxPdu = 253;
constexpr std::uint8_t kBytesPerRegister = 2;

// SMSMB identity (SPEC §2.4, discovery.h): read at discovery; its first register answers PINGs.
const IdentityLayout& smsmb_identity() { return *identity_layout(modbus_map::TableId::Smsmb); }
// SMSMB status register: its low byte is what input register 1000 shows as "last status".
constexpr std::uint16_t kSmsmbStatusRegister = 0x100;

// The answer a request is waiting for.
enum class ReplyShape : std::uint8_t {
  Registers,       // FC03: byte count 2n, n registers
  Echo,            // FC06: the request PDU itself
  WriteMultiple,   // FC16: function, address, quantity (the request's first five bytes)
  AnyOfFunction,   // passthrough and PING: any answer to this function code, exceptions included
};

// Standard exception names, for logs (Modbus application protocol v1.1b3 §7).
std::string_view exception_name(std::uint8_t code) {
  switch (code) {
    case 0x01: return "illegal function";
    case 0x02: return "illegal data address";
    case 0x03: return "illegal data value";
    case 0x04: return "server device failure";
    case 0x05: return "acknowledge";
    case 0x06: return "server device busy";
    case 0x08: return "memory parity error";
    case 0x0A: return "gateway path unavailable";
    case 0x0B: return "gateway target failed to respond";
    default: return "unknown exception";
  }
}

// A reply's size for the reply timeout: exact where the function says it, else the largest.
std::size_t expected_reply_bytes(std::span<const std::uint8_t> pdu) {
  const auto quantity = [&](std::size_t at) -> std::size_t {
    return pdu.size() >= at + 2 ? static_cast<std::size_t>(pdu[at] << 8 | pdu[at + 1]) : 0;
  };
  switch (pdu[0]) {
    case 0x01:
    case 0x02: return 5 + (quantity(3) + 7) / 8;
    case 0x03:
    case 0x04: return 5 + 2 * quantity(3);
    case 0x05:
    case 0x06:
    case 0x0F:
    case 0x10: return 8;
    case 0x17: return 5 + 2 * quantity(3);
    default: return protocol::rtu::kMaxAduSize;
  }
}

struct Job {
  std::uint8_t slave = 0;
  Bytes pdu;
  ReplyShape shape = ReplyShape::AnyOfFunction;
  std::uint16_t registers = 0;  // Registers: how many
  bool broadcast = false;       // no reply awaited (slave 0, or a write the servo does not answer)
  bool forward_exceptions = false;  // RawPduOp: an exception PDU is the answer, passed on as it is
  unsigned attempts = 1;
  bool client = false;
  MotionEpoch motion_epoch = 0;  // motion_refusal() just before the job goes on the wire
  SteadyClock::time_point queued_at{};  // the age rule of next_client_job
  Completion done;
};

enum class WorkKind : std::uint8_t { Identity, PollRead, Probe };
struct Work {
  WorkKind kind;
  std::uint8_t servo_id;
  SteadyClock::time_point queued_at = SteadyClock::now();  // the age rule of next_client_job
};

std::uint32_t saturate_us(SteadyClock::duration duration) {
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(duration).count();
  return static_cast<std::uint32_t>(std::clamp<std::int64_t>(us, 0, 0xFFFFFFFF));
}

Bytes read_pdu(std::uint16_t address, std::uint16_t count) {
  return {fc::kReadHoldingRegisters, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address),
          static_cast<std::uint8_t>(count >> 8), static_cast<std::uint8_t>(count)};
}

BusSettings validated(BusSettings settings) {
  const std::string where = "bus " + settings.name + ": ";
  if (settings.protocol != protocol::BusProtocol::ModbusRtu) {
    throw std::invalid_argument(where + "RtuBusEngine runs modbus-rtu buses only");
  }
  if (settings.serial.baud == 0) throw std::invalid_argument(where + "baud must not be 0");
  if (settings.queue_depth == 0) throw std::invalid_argument(where + "queue depth must be at least 1");
  std::array<bool, 256> seen{};
  for (const auto& servo : settings.servos) {
    const auto& table = modbus_map::table(servo.table);
    const std::string who = where + "servo " + std::to_string(servo.servo_id) + " (" + std::string(table.name) + "): ";
    if (table.protocol != protocol::BusProtocol::ModbusRtu) {
      throw std::invalid_argument(who + "its table is spoken over " + std::string(protocol::to_string(table.protocol)) +
                                  ", not over this modbus-rtu bus");
    }
    if (servo.servo_id < 1 || servo.servo_id > kMaxSlave) {
      throw std::invalid_argument(who + "a Modbus slave address is 1-247");
    }
    if (seen[servo.servo_id]) throw std::invalid_argument(who + "configured twice on this bus");
    seen[servo.servo_id] = true;
    const auto& block = servo.poll_block;
    if (block.count == 0 || block.count > kMaxReadRegisters || std::uint32_t{block.address} + block.count > 0x10000) {
      throw std::invalid_argument(who + fmt::format("poll block 0x{:04X}+{} cannot be read with one FC03 "
                                                    "(1-125 registers)", block.address, block.count));
    }
  }
  return settings;
}

std::vector<PollCache::ServoEntry> cache_entries(const BusSettings& settings) {
  std::vector<PollCache::ServoEntry> entries;
  for (const auto& servo : settings.servos) entries.push_back({servo.servo_id, servo.poll_block});
  return entries;
}

std::vector<PollTarget> poll_targets(const BusSettings& settings) {
  std::vector<PollTarget> targets;
  for (const auto& servo : settings.servos) targets.push_back({servo.servo_id, servo.poll_block, false});
  return targets;
}

}  // namespace

class RtuBusEngine::Impl {
 public:
  Impl(BusSettings settings, config::ModbusRtuOptions options)
      : settings_(validated(std::move(settings))),
        master_(RtuLineSettings{settings_.serial, options}),
        // SMSMB registers are two bytes each (high byte first), as the unit router copies them.
        cache_(cache_entries(settings_), kBytesPerRegister),
        scheduler_(poll_targets(settings_), settings_.probe_period) {}
  ~Impl() { stop(); }

  void start();
  void stop();
  void submit(BusOp op, Priority priority, Completion done);

  const BusSettings& settings() const { return settings_; }
  bool bus_up() const { return bus_up_.load(); }
  BusCountersSnapshot counters() const { return counters_.snapshot(); }
  const PollCache& cache() const { return cache_; }
  bool discovered() const { return discovered_.load(); }

 private:
  Job make_client_job(BusOp&& op) const;

  void run_thread();
  bool try_open();
  void bus_came_up();
  void port_lost(const std::string& reason);
  // Waits for the next thing to do; a client job when one is queued. nullopt: stop, or
  // internal work (discovery, poll) is due.
  std::optional<Job> next_client_job();
  void run_client_job(Job job);
  BusResult execute(const Job& job);
  BusResult check_reply(const Job& job, Bytes reply) const;
  void run_work(Work work);
  void start_cycle();
  void finish_cycle_if_done();
  void servo_answered(std::uint8_t servo_id);
  void servo_silent(std::uint8_t servo_id, const std::string& reason, bool log);
  std::chrono::nanoseconds reply_timeout(const Job& job) const;
  void fail_queued(BusStatus status, const std::string& detail);

  const BusSettings settings_;
  RtuMaster master_;
  PollCache cache_;
  PollScheduler scheduler_;  // bus thread only
  BusCounters counters_;
  std::atomic<bool> bus_up_{false};
  std::atomic<bool> discovered_{false};

  std::mutex mutex_;
  std::condition_variable wake_;
  std::bitset<256> poll_refusal_logged_;  // servos whose refused poll was logged (bus thread)
  JobQueue<Job> queue_;  // client jobs only (the engine's own work is in work_)
  // next_client_job's age rule: client work after kClientAgeLimit, the engine's own work after
  // one poll period (at least 10 ms).
  static constexpr std::array<std::chrono::nanoseconds, kPriorityCount> client_age_limits_{
      std::chrono::nanoseconds{0}, kClientAgeLimit, kClientAgeLimit, kClientAgeLimit};
  std::chrono::nanoseconds internal_age_limit_ = std::max<std::chrono::nanoseconds>(settings_.poll_period, 10ms);
  bool accepting_ = false;
  bool stopping_ = false;
  std::thread thread_;

  // Bus thread only.
  std::deque<Work> work_;
  bool cycle_running_ = false;
  SteadyClock::time_point cycle_started_{};
  SteadyClock::time_point next_cycle_{};
  std::size_t discovery_pending_ = 0;
  std::vector<DiscoveredServo> discovery_;
  bool open_failure_logged_ = false;
};

// ---- queue ------------------------------------------------------------------------------------

Job RtuBusEngine::Impl::make_client_job(BusOp&& op) const {
  const std::string where = "bus " + settings_.name + ": ";
  Job job;
  job.client = true;
  job.attempts = 1 + settings_.retries;
  if (auto* read = std::get_if<ReadOp>(&op)) {
    if (read->servo_id < 1 || read->servo_id > kMaxSlave) {
      throw std::invalid_argument(where + "FC03 reads go to slaves 1-247, not " + std::to_string(read->servo_id));
    }
    if (read->count < 1 || read->count > kMaxReadRegisters) {
      throw std::invalid_argument(where + "FC03 reads 1-125 registers, not " + std::to_string(read->count));
    }
    job.slave = read->servo_id;
    job.pdu = read_pdu(read->address, read->count);
    job.shape = ReplyShape::Registers;
    job.registers = read->count;
  } else if (auto* write = std::get_if<WriteOp>(&op)) {
    if (write->staged) throw std::invalid_argument(where + "Modbus has no staged (REG WRITE) writes");
    const std::size_t registers = write->data.size() / 2;
    if (write->data.size() % 2 != 0 || registers < 1 || registers > kMaxWriteRegisters) {
      throw std::invalid_argument(where + "a write carries 1-123 registers (2 bytes each), not " +
                                  std::to_string(write->data.size()) + " bytes");
    }
    if (write->servo_id > kMaxSlave) {
      throw std::invalid_argument(where + "writes go to slaves 1-247 or 0 (broadcast), not " +
                                  std::to_string(write->servo_id));
    }
    job.slave = write->servo_id;
    const auto address_hi = static_cast<std::uint8_t>(write->address >> 8);
    const auto address_lo = static_cast<std::uint8_t>(write->address);
    if (registers == 1) {
      job.pdu = {fc::kWriteSingleRegister, address_hi, address_lo, write->data[0], write->data[1]};
      job.shape = ReplyShape::Echo;
    } else {
      // Sized once and filled in place (GCC 12 -O2 misreads an insert after a braced init as
      // out of bounds: -Warray-bounds).
      constexpr std::size_t kHeader = 6;
      job.pdu.assign(kHeader + write->data.size(), 0);
      job.pdu[0] = fc::kWriteMultipleRegisters;
      job.pdu[1] = address_hi;
      job.pdu[2] = address_lo;
      job.pdu[4] = static_cast<std::uint8_t>(registers);
      job.pdu[5] = static_cast<std::uint8_t>(write->data.size());
      std::copy(write->data.begin(), write->data.end(), job.pdu.begin() + kHeader);
      job.shape = ReplyShape::WriteMultiple;
    }
    job.broadcast = write->servo_id == kBroadcastSlave || !write->expect_reply;
  } else if (auto* ping = std::get_if<PingOp>(&op)) {
    if (ping->servo_id < 1 || ping->servo_id > kMaxSlave) {
      throw std::invalid_argument(where + "PING goes to slaves 1-247, not " + std::to_string(ping->servo_id));
    }
    job.slave = ping->servo_id;
    job.pdu = read_pdu(smsmb_identity().read.address, 1);
    job.shape = ReplyShape::AnyOfFunction;
  } else if (auto* raw = std::get_if<RawPduOp>(&op)) {
    if (raw->pdu.empty() || raw->pdu.size() > kMaxPdu) {
      throw std::invalid_argument(where + "a PDU is 1-253 bytes, not " + std::to_string(raw->pdu.size()));
    }
    if (raw->slave > kMaxSlave) {
      throw std::invalid_argument(where + "slave addresses are 1-247 or 0 (broadcast), not " +
                                  std::to_string(raw->slave));
    }
    job.slave = raw->slave;
    job.pdu = std::move(raw->pdu);
    job.shape = ReplyShape::AnyOfFunction;
    job.forward_exceptions = true;
    job.broadcast = raw->slave == kBroadcastSlave;
  } else if (std::holds_alternative<ActionOp>(op)) {
    throw std::invalid_argument(where + "Modbus has no ACTION: staged writes exist on packet buses only");
  } else {
    throw std::invalid_argument(where + "Modbus has no SYNC WRITE: sync groups need packet buses");
  }
  if (job.broadcast) job.attempts = 1;  // nothing tells whether it arrived: never sent twice
  return job;
}

void RtuBusEngine::Impl::submit(BusOp op, Priority priority, Completion done) {
  const MotionEpoch motion_epoch = motion_epoch_of(op);
  Job job = make_client_job(std::move(op));
  job.motion_epoch = motion_epoch;
  job.done = std::move(done);
  if (queue_client_job(settings_, counters_, mutex_, queue_, std::move(job), priority, accepting_, bus_up_.load())) {
    wake_.notify_one();
  }
}

void RtuBusEngine::Impl::fail_queued(BusStatus status, const std::string& detail) {
  std::vector<Job> failed;
  {
    std::lock_guard lock(mutex_);
    failed = queue_.take_clients();
  }
  for (auto& job : failed) complete(settings_, job.done, BusResult{status, 0, {}, detail});
}

// ---- thread -----------------------------------------------------------------------------------

void RtuBusEngine::Impl::start() {
  {
    std::lock_guard lock(mutex_);
    if (accepting_ || thread_.joinable()) throw std::logic_error("bus " + settings_.name + ": start() called twice");
    accepting_ = true;
  }
  if (try_open()) bus_came_up();
  thread_ = std::thread([this] { run_thread(); });
}

void RtuBusEngine::Impl::stop() {
  {
    std::lock_guard lock(mutex_);
    accepting_ = false;
    stopping_ = true;
  }
  wake_.notify_all();
  if (!thread_.joinable()) return;
  if (std::this_thread::get_id() == thread_.get_id()) {
    throw std::logic_error("bus " + settings_.name + ": stop() called from the bus thread (inside a completion)");
  }
  thread_.join();
}

void RtuBusEngine::Impl::run_thread() {
  // Every frame waits for frame_gap (0.3-1.75 ms at 115 200 bit/s) in a sleep: Linux's default
  // 50 us timer slack on that sleep would be line time lost before each frame.
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
  for (;;) {
    try {
      for (;;) {
        if (!master_.is_open()) {
          std::unique_lock lock(mutex_);
          if (wake_.wait_for(lock, settings_.reopen_period, [this] { return stopping_; })) break;
          lock.unlock();
          if (try_open()) bus_came_up();
          continue;
        }
        std::optional<Job> job = next_client_job();
        {
          std::lock_guard lock(mutex_);
          if (stopping_) {
            if (job) queue_.push_front(std::move(*job), Priority::Safety);  // failed with the rest below
            break;
          }
        }
        if (job) {
          run_client_job(std::move(*job));
        } else if (!work_.empty()) {
          const Work work = work_.front();
          work_.pop_front();
          run_work(work);
        } else if (discovered_.load() && settings_.poll && !cycle_running_ && SteadyClock::now() >= next_cycle_) {
          start_cycle();
        }
      }
      break;
    } catch (const std::exception& error) {
      spdlog::critical("bus {}: internal error on the bus thread: {}", settings_.name, error.what());
    }
  }
  master_.close();
  bus_up_.store(false);
  fail_queued(BusStatus::Cancelled, "bus " + settings_.name + ": the gateway is stopping");
}

std::optional<Job> RtuBusEngine::Impl::next_client_job() {
  std::unique_lock lock(mutex_);
  for (;;) {
    if (stopping_) return std::nullopt;
    // The same order as every bus (next_level(), bus_engine.h): safe stops first; the engine's
    // own poll, probe or identity work that has waited one poll period (at least 10 ms) next,
    // so a client flood cannot freeze the poll cache or keep an offline servo from its probe;
    // then client work by priority, with the client age rule. Overdue work of both kinds goes
    // oldest first, as next_level() orders it.
    const auto now = SteadyClock::now();
    const bool polling = discovered_.load() && settings_.poll && !settings_.servos.empty() && !cycle_running_;
    const bool safety_waiting = !queue_.empty(Priority::Safety);
    // Since when the engine's own work waits: its first queued item, else the due poll cycle.
    std::optional<SteadyClock::time_point> internal_since;
    if (!work_.empty()) {
      internal_since = work_.front().queued_at;
    } else if (polling) {
      internal_since = next_cycle_;
    }
    const auto level = queue_.next(client_age_limits_, now);
    if (!safety_waiting && internal_since && now - *internal_since >= internal_age_limit_) {
      const bool older_client_overdue = level && now - queue_.front(*level).queued_at >= client_age_limits_[*level] &&
                                        queue_.front(*level).queued_at < *internal_since;
      if (!older_client_overdue) return std::nullopt;
    }
    if (level) return queue_.pop(*level);
    if (!work_.empty()) return std::nullopt;
    if (polling && now >= next_cycle_) return std::nullopt;
    if (polling) {
      wake_.wait_until(lock, next_cycle_);
    } else {
      wake_.wait(lock);
    }
  }
}

bool RtuBusEngine::Impl::try_open() {
  auto opened = master_.open();
  if (!opened) {
    if (!open_failure_logged_) {
      spdlog::error("bus {}: {}; retrying every {} ms", settings_.name, opened.error(),
                    settings_.reopen_period.count());
      open_failure_logged_ = true;
    }
    return false;
  }
  open_failure_logged_ = false;
  spdlog::info("bus {}: {} open, modbus-rtu at {} bit/s{}", settings_.name, settings_.serial.device,
               settings_.serial.baud, libmodbus_sets_rate(settings_.serial.baud) ? "" : " (termios2 rate)");
  return true;
}

void RtuBusEngine::Impl::bus_came_up() {
  scheduler_.forget_all();
  cache_.set_all_offline();
  work_.clear();
  cycle_running_ = false;
  discovered_.store(false);
  bus_up_.store(true);
  discovery_.clear();
  if (!settings_.discover || settings_.servos.empty()) {
    discovered_.store(true);
    next_cycle_ = SteadyClock::now();
    return;
  }
  for (const auto& servo : settings_.servos) {
    DiscoveredServo found;
    found.servo_id = servo.servo_id;
    found.table = servo.table;
    discovery_.push_back(found);
    work_.push_back({WorkKind::Identity, servo.servo_id});
  }
  discovery_pending_ = settings_.servos.size();
}

void RtuBusEngine::Impl::port_lost(const std::string& reason) {
  master_.close();
  counters_.bus_down_events.fetch_add(1, std::memory_order_relaxed);
  // Before the bus reads down: whoever sees bus_up() false sees the loss counted and every
  // servo offline too.
  cache_.set_all_offline();
  discovered_.store(false);
  bus_up_.store(false);
  spdlog::error("bus {}: serial port lost ({}); reopening every {} ms", settings_.name, reason,
                settings_.reopen_period.count());
  open_failure_logged_ = true;  // the loss is the message; do not repeat it for each reopen attempt
  scheduler_.forget_all();
  work_.clear();
  cycle_running_ = false;
  fail_queued(BusStatus::BusDown, "bus " + settings_.name + ": serial port " + settings_.serial.device + " lost");
}

// ---- transactions -----------------------------------------------------------------------------

std::chrono::nanoseconds RtuBusEngine::Impl::reply_timeout(const Job& job) const {
  return master_.wire_time(expected_reply_bytes(job.pdu)) + settings_.response_timeout;
}

void RtuBusEngine::Impl::run_client_job(Job job) {
  BusResult result;
  if (auto refusal = motion_refusal(settings_, job.motion_epoch)) {
    result = std::move(*refusal);
  } else if (job.slave != kBroadcastSlave && scheduler_.presence(job.slave) == Presence::Offline) {
    // As on packet buses: a client polling a dead servo must not make the bus pay timeouts;
    // the servo's probe brings it back within one probe period.
    result = BusResult{BusStatus::Timeout, 0, {},
                       fmt::format("bus {}: servo {} is offline (it stopped answering; probed every {} ms)",
                                   settings_.name, job.slave, settings_.probe_period.count())};
  } else {
    result = execute(job);
  }
  counters_.transactions.fetch_add(1, std::memory_order_relaxed);
  complete(settings_, job.done, std::move(result));
}

BusResult RtuBusEngine::Impl::execute(const Job& job) {
  const std::string where = fmt::format("bus {}: slave {} FC{:02X}", settings_.name, job.slave, job.pdu[0]);
  if (job.broadcast) {
    const RtuExchange sent = master_.send_only(job.slave, job.pdu, settings_.response_timeout);
    if (sent.outcome == RtuOutcome::PortError) {
      port_lost(sent.detail);
      return {BusStatus::BusDown, 0, {}, where + ": " + sent.detail};
    }
    return {BusStatus::Ok, 0, {}, {}};
  }
  ServoCounters* servo = cache_.counters(job.slave);
  bool corrupt = false;
  std::string last_problem;
  for (unsigned attempt = 0; attempt < job.attempts; ++attempt) {
    if (attempt > 0) counters_.retries.fetch_add(1, std::memory_order_relaxed);
    RtuExchange exchange = master_.transact(job.slave, job.pdu, reply_timeout(job));
    switch (exchange.outcome) {
      case RtuOutcome::Reply: {
        BusResult result = check_reply(job, std::move(exchange.pdu));
        if (result.status == BusStatus::Corrupt) {
          counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
          corrupt = true;
          last_problem = result.detail;
          continue;
        }
        counters_.frames_ok.fetch_add(1, std::memory_order_relaxed);
        if (servo != nullptr) servo->replies_ok.fetch_add(1, std::memory_order_relaxed);
        return result;
      }
      case RtuOutcome::Timeout:
        counters_.timeouts.fetch_add(1, std::memory_order_relaxed);
        if (servo != nullptr) servo->timeouts.fetch_add(1, std::memory_order_relaxed);
        last_problem = exchange.detail;
        break;
      case RtuOutcome::Corrupt:
        counters_.checksum_errors.fetch_add(1, std::memory_order_relaxed);
        corrupt = true;
        last_problem = exchange.detail;
        break;
      case RtuOutcome::WrongSlave:
        counters_.stray_frames.fetch_add(1, std::memory_order_relaxed);
        corrupt = true;
        last_problem = exchange.detail;
        break;
      case RtuOutcome::PortError:
        port_lost(exchange.detail);
        return {BusStatus::BusDown, 0, {}, where + ": " + exchange.detail};
      case RtuOutcome::Sent:
        break;
    }
  }
  const auto attempts = fmt::format("{} attempt{}", job.attempts, job.attempts == 1 ? "" : "s");
  if (corrupt) return {BusStatus::Corrupt, 0, {}, where + ": answers stayed corrupt (" + attempts + "): " + last_problem};
  return {BusStatus::Timeout, 0, {}, where + ": no answer (" + attempts + "): " + last_problem};
}

BusResult RtuBusEngine::Impl::check_reply(const Job& job, Bytes reply) const {
  const std::uint8_t requested = job.pdu[0];
  const std::string where = fmt::format("bus {}: slave {} FC{:02X}", settings_.name, job.slave, requested);
  const auto corrupt = [&](std::string_view what) {
    return BusResult{BusStatus::Corrupt, 0, {}, fmt::format("{}: {}: {}", where, what, hex(reply))};
  };
  if (reply.empty()) return corrupt("empty answer");
  if (reply[0] == (requested | fc::kExceptionBit)) {
    if (reply.size() != 2) return corrupt("malformed exception answer");
    if (job.forward_exceptions || (job.shape == ReplyShape::AnyOfFunction)) {
      return {BusStatus::Ok, reply[1], std::move(reply), {}};
    }
    return {BusStatus::ServoRefused, reply[1], {},
            fmt::format("{}: the slave answered exception 0x{:02X} ({})", where, reply[1], exception_name(reply[1]))};
  }
  if (reply[0] != requested) return corrupt(fmt::format("answer with function 0x{:02X}", reply[0]));
  switch (job.shape) {
    case ReplyShape::Registers: {
      const std::size_t bytes = std::size_t{job.registers} * 2;
      if (reply.size() != 2 + bytes || reply[1] != bytes) return corrupt("register count differs from the request");
      return {BusStatus::Ok, 0, Bytes(reply.begin() + 2, reply.end()), {}};
    }
    case ReplyShape::Echo:
      if (reply != job.pdu) return corrupt("FC06 answer is not the echo of the request");
      return {BusStatus::Ok, 0, {}, {}};
    case ReplyShape::WriteMultiple:
      if (reply.size() != 5 || !std::equal(reply.begin(), reply.end(), job.pdu.begin())) {
        return corrupt("FC16 answer does not repeat address and quantity");
      }
      return {BusStatus::Ok, 0, {}, {}};
    case ReplyShape::AnyOfFunction:
      return {BusStatus::Ok, 0, std::move(reply), {}};
  }
  return corrupt("unexpected answer");
}

// ---- discovery and polling -----------------------------------------------------------------------

void RtuBusEngine::Impl::run_work(Work work) {
  const auto target = scheduler_.target(work.servo_id);
  if (target == nullptr) return;
  Job job;
  job.slave = work.servo_id;
  job.shape = ReplyShape::Registers;
  if (work.kind == WorkKind::Identity) {
    job.pdu = read_pdu(smsmb_identity().read.address, smsmb_identity().read.count);
    job.registers = smsmb_identity().read.count;
    job.attempts = 1 + settings_.retries;
  } else {
    job.pdu = read_pdu(target->block.address, target->block.count);
    job.registers = target->block.count;
    // A probe is one attempt: an offline servo costs at most one timeout per probe period.
    job.attempts = work.kind == WorkKind::Probe ? 1 : 1 + settings_.retries;
  }
  const BusResult result = execute(job);
  counters_.transactions.fetch_add(1, std::memory_order_relaxed);
  if (result.status == BusStatus::BusDown) return;  // port_lost() reset everything

  if (work.kind == WorkKind::Identity) {
    auto found = std::find_if(discovery_.begin(), discovery_.end(),
                              [&](const DiscoveredServo& servo) { return servo.servo_id == work.servo_id; });
    if (result.status == BusStatus::Ok) {
      const ServoIdentity identity = decode_identity(smsmb_identity(), result.data, modbus_map::ByteOrder::HighFirst);
      cache_.set_identity(work.servo_id, identity);
      servo_answered(work.servo_id);
      if (found != discovery_.end()) {
        found->online = true;
        found->identity = identity;
      }
    } else {
      const std::string reason = result.status == BusStatus::Timeout
                                     ? fmt::format("no answer to FC03 ({} attempts)", job.attempts)
                                     : std::string(to_string(result.status)) + ": " + result.detail;
      if (result.status == BusStatus::ServoRefused) {
        servo_answered(work.servo_id);  // it is there, though not an SMSMB servo
        if (found != discovery_.end()) found->online = true;
        spdlog::warn("{} — is this slave really an SMSMB servo (table smsmb)?", result.detail);
      } else {
        servo_silent(work.servo_id, reason, false);
        if (found != discovery_.end()) found->detail = reason;
      }
    }
    if (discovery_pending_ > 0 && --discovery_pending_ == 0) {
      spdlog::info("{}", format_discovery_summary({settings_.name, settings_.serial.device, "modbus-rtu",
                                                   settings_.serial.baud, discovery_}));
      discovered_.store(true);
      next_cycle_ = SteadyClock::now();
    }
    return;
  }

  switch (result.status) {
    case BusStatus::Ok: {
      const auto now = SteadyClock::now();
      cache_.store_block(work.servo_id, result.data, now);
      poll_refusal_logged_.reset(work.servo_id);
      const AddressBlock& block = target->block;
      if (block.contains(kSmsmbStatusRegister, 1)) {
        const auto offset = static_cast<std::size_t>(kSmsmbStatusRegister - block.address) * 2;
        if (ServoCounters* counters = cache_.counters(work.servo_id)) {
          // Logged once per change, as on packet buses (docs/DECISIONS.md "Gateway", the status byte).
          const std::uint8_t status = result.data[offset + 1];
          const auto previous = counters->last_status.exchange(status, std::memory_order_relaxed);
          if (previous != status) {
            spdlog::info("bus {}: servo {} status byte 0x{:02X} -> 0x{:02X}", settings_.name, work.servo_id, previous,
                         status);
          }
        }
      }
      servo_answered(work.servo_id);
      break;
    }
    case BusStatus::ServoRefused:
      servo_answered(work.servo_id);
      // Once per episode, not every cycle: the configuration will not change by itself.
      if (!poll_refusal_logged_.test(work.servo_id)) {
        spdlog::warn("{} — check the poll range configured for this bus (said once until a poll succeeds)",
                     result.detail);
        poll_refusal_logged_.set(work.servo_id);
      }
      break;
    case BusStatus::Timeout:
    case BusStatus::Corrupt:
      servo_silent(work.servo_id, work.kind == WorkKind::Probe ? "probe unanswered" : result.detail, true);
      break;
    default:
      break;
  }
  finish_cycle_if_done();
}

void RtuBusEngine::Impl::start_cycle() {
  const auto now = SteadyClock::now();
  const PollCyclePlan plan = scheduler_.plan_cycle(now);
  if (plan.reads.empty() && plan.probes.empty()) {
    // Nobody online and no probe due yet: wake up for the next probe.
    const auto due = scheduler_.next_probe_due();
    next_cycle_ = due ? std::max(*due, now + settings_.poll_period) : now + std::max(settings_.poll_period, 100ms);
    return;
  }
  cycle_running_ = true;
  cycle_started_ = now;
  for (const auto id : plan.reads) work_.push_back({WorkKind::PollRead, id});
  for (const auto id : plan.probes) work_.push_back({WorkKind::Probe, id});
}

void RtuBusEngine::Impl::finish_cycle_if_done() {
  if (!cycle_running_ || !work_.empty()) return;
  const auto now = SteadyClock::now();
  cycle_running_ = false;
  counters_.poll_cycles.fetch_add(1, std::memory_order_relaxed);
  counters_.last_poll_cycle_us.store(saturate_us(now - cycle_started_), std::memory_order_relaxed);
  next_cycle_ = std::max(cycle_started_ + settings_.poll_period, now);
}

void RtuBusEngine::Impl::servo_answered(std::uint8_t servo_id) {
  const PresenceChange change = scheduler_.answered(servo_id);
  cache_.set_online(servo_id, true);
  if (change == PresenceChange::CameOnline) {
    spdlog::info("bus {}: servo {} answers again: online", settings_.name, servo_id);
  }
}

void RtuBusEngine::Impl::servo_silent(std::uint8_t servo_id, const std::string& reason, bool log) {
  const PresenceChange change = scheduler_.silent(servo_id, SteadyClock::now());
  cache_.set_online(servo_id, false);
  if (log && change == PresenceChange::WentOffline) {
    spdlog::warn("bus {}: servo {} offline ({}); probing it every {} ms", settings_.name, servo_id, reason,
                 settings_.probe_period.count());
  }
}

// ---- public face --------------------------------------------------------------------------------

RtuBusEngine::RtuBusEngine(BusSettings settings, config::ModbusRtuOptions options)
    : impl_(std::make_unique<Impl>(std::move(settings), options)) {}
RtuBusEngine::~RtuBusEngine() = default;
void RtuBusEngine::start() { impl_->start(); }
void RtuBusEngine::stop() { impl_->stop(); }
void RtuBusEngine::submit(BusOp op, Priority priority, Completion done) {
  impl_->submit(std::move(op), priority, std::move(done));
}
const BusSettings& RtuBusEngine::settings() const { return impl_->settings(); }
bool RtuBusEngine::bus_up() const { return impl_->bus_up(); }
BusCountersSnapshot RtuBusEngine::counters() const { return impl_->counters(); }
const PollCache& RtuBusEngine::cache() const { return impl_->cache(); }
bool RtuBusEngine::discovered() const { return impl_->discovered(); }

}  // namespace sms::gateway
