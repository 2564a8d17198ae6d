#include "gateway/bus/rtu_master.h"

#include <fcntl.h>
#include <modbus/modbus.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstring>
#include <stdexcept>
#include <thread>

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include "gateway/bus/serial_port_termios2.h"
#include "protocol/hex_text.h"
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
    110,    300,    600,    1200,   2400,    4800,    9600,    19200,   38400,   57600,   115200, 230400,
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
    case config::FrameGap::Kind::Characters: return three_and_a_half_characters;
    case config::FrameGap::Kind::Fixed: return gap.fixed;
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
    case EPERM: return " — no permission: add the user to the group owning the device (usually `dialout`)";
    case EBUSY: return " — another program holds the device (fuser -v DEVICE shows which)";
    case ENOTTY:
    case EINVAL: return " — this is not a serial device, or its driver refuses these line settings";
    default: return "";
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
  return static_cast<int>(
      std::min<std::int64_t>(std::chrono::ceil<std::chrono::milliseconds>(timeout).count(), 60'000));
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
  modbus_t* context = modbus_new_rtu(serial.device.c_str(), static_cast<int>(serial.baud), parity_letter(serial.parity),
                                     8, serial.stop_bits == 2 ? 2 : 1);
  if (context == nullptr)
    return unexpected("cannot set up a Modbus RTU line on " + where + ": " + modbus_strerror(errno));
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
  if (const int error = detail::configure_raw_line(fd, serial.baud, serial.parity, serial.stop_bits); error != 0) {
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
  if (detail::read_line_speed(fd, actual) == 0 && actual != 0 && actual != serial.baud) {
    spdlog::warn("{}: the driver runs the line at {} bit/s instead of {}", serial.device, actual, serial.baud);
  }
  line_->context = context;
  line_->quiet_since = SteadyClock::now();
  return Ok{};
}

Expected<Ok> RtuMaster::set_baud(std::uint32_t baud) {
  settings_.serial.baud = baud;
  if (!is_open()) return Ok{};
  close();
  return open();
}

void RtuMaster::wait_for_frame_gap() {
  const auto ready = line_->quiet_since + rtu_frame_gap(settings_.serial, settings_.options.frame_gap);
  const auto now = SteadyClock::now();
  if (ready > now) std::this_thread::sleep_for(ready - now);
}

RtuMaster::Sending RtuMaster::send_request(std::uint8_t slave, std::span<const std::uint8_t> pdu,
                                           std::string_view caller,
                                           std::optional<std::chrono::nanoseconds> answer_within) {
  Sending sending;
  if (!is_open()) {
    sending.failure = RtuExchange{RtuOutcome::PortError, {}, settings_.serial.device + " is not open"};
    return sending;
  }
  if (pdu.empty() || pdu.size() > protocol::rtu::kMaxPduSize) {
    throw std::invalid_argument("RtuMaster::" + std::string(caller) + ": a PDU is 1 to 253 bytes, not " +
                                std::to_string(pdu.size()));
  }
  modbus_t* context = line_->context;
  wait_for_frame_gap();
  sending.dropped = drop_input();  // late replies and noise would otherwise be read as this answer
  modbus_set_slave(context, slave);
  sending.request.reserve(pdu.size() + 1);
  sending.request.push_back(slave);
  sending.request.insert(sending.request.end(), pdu.begin(), pdu.end());
  if (answer_within) {
    // The reply timeout counts from when the request has left the wire (write() returns at once).
    sending.response_timeout = wire_time(sending.request.size() + 2) + *answer_within;
    std::uint32_t seconds = 0;
    std::uint32_t micros = 0;
    split_timeout(sending.response_timeout, seconds, micros);
    modbus_set_response_timeout(context, seconds, micros);
  }
  if (modbus_send_raw_request(context, sending.request.data(), static_cast<int>(sending.request.size())) < 0) {
    const int error = errno;
    sending.failure =
        RtuExchange{RtuOutcome::PortError, {}, "write to " + settings_.serial.device + ": " + modbus_strerror(error)};
    return sending;
  }
  tap_request(sending.request);
  return sending;
}

RtuExchange RtuMaster::transact(std::uint8_t slave, std::span<const std::uint8_t> pdu,
                                std::chrono::nanoseconds reply_timeout) {
  Sending sending = send_request(slave, pdu, "transact", reply_timeout);
  if (sending.failure) return std::move(*sending.failure);
  RtuExchange exchange = receive_answer(slave, pdu[0], sending.response_timeout);
  exchange.dropped = std::move(sending.dropped);
  return exchange;
}

RtuExchange RtuMaster::receive_answer(std::uint8_t slave, std::uint8_t function,
                                      std::chrono::nanoseconds response_timeout) {
  modbus_t* context = line_->context;
  if (!libmodbus_sizes(function)) return receive_until_silence(slave, response_timeout);

  std::array<std::uint8_t, MODBUS_RTU_MAX_ADU_LENGTH> answer{};
  const int received = modbus_receive_confirmation(context, answer.data());
  const int error = errno;
  if (received > 0) tap(WireDirection::FromServos, std::span(answer).first(static_cast<std::size_t>(received)));
  line_->quiet_since = SteadyClock::now();
  if (received < 0) {
    switch (error) {
      case ETIMEDOUT:
        return {RtuOutcome::Timeout,
                {},
                fmt::format("no answer from slave {} within {} us", slave,
                            std::chrono::duration_cast<std::chrono::microseconds>(response_timeout).count())};
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
    RtuExchange exchange{
        RtuOutcome::WrongSlave, {}, fmt::format("asked slave {}, a frame from another slave came", slave)};
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
      return {RtuOutcome::PortError,
              {},
              "read from " + settings_.serial.device + ": " +
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
  tap(WireDirection::FromServos, frame);
  if (frame.empty()) return {RtuOutcome::Timeout, {}, fmt::format("no answer from slave {}", slave)};
  if (frame.size() < protocol::rtu::kMinAduSize ||
      protocol::rtu::crc16(std::span(frame).first(frame.size() - 2)) !=
          static_cast<std::uint16_t>(frame[frame.size() - 2] | frame[frame.size() - 1] << 8)) {
    return {RtuOutcome::Corrupt,
            {},
            fmt::format("answer from slave {} with a wrong CRC: {}", slave, protocol::hex_bytes(frame))};
  }
  if (frame[0] != slave) {
    return {RtuOutcome::WrongSlave, {}, fmt::format("asked slave {}, slave {} answered", slave, frame[0]), frame[0]};
  }
  return {RtuOutcome::Reply, Bytes(frame.begin() + 1, frame.end() - 2), {}};
}

RtuExchange RtuMaster::send_only(std::uint8_t slave, std::span<const std::uint8_t> pdu,
                                 std::chrono::nanoseconds turnaround) {
  Sending sending = send_request(slave, pdu, "send_only", std::nullopt);
  if (sending.failure) return std::move(*sending.failure);
  std::this_thread::sleep_for(wire_time(sending.request.size() + 2) + turnaround);
  line_->quiet_since = SteadyClock::now();
  RtuExchange sent{RtuOutcome::Sent, {}, {}};
  sent.dropped = std::move(sending.dropped);
  return sent;
}

Bytes RtuMaster::drop_input() {
  const int fd = modbus_get_socket(line_->context);
  std::array<std::uint8_t, 256> buffer{};
  Bytes dropped;
  for (;;) {
    pollfd descriptor{fd, POLLIN, 0};
    if (::poll(&descriptor, 1, 0) <= 0 || (descriptor.revents & POLLIN) == 0) break;
    const ssize_t got = ::read(fd, buffer.data(), buffer.size());
    if (got <= 0) break;  // a lost device is reported by the exchange that follows
    const auto bytes = std::span(buffer).first(static_cast<std::size_t>(got));
    tap(WireDirection::FromServos, bytes);
    dropped.insert(dropped.end(), bytes.begin(), bytes.end());
  }
  if (!dropped.empty()) line_->quiet_since = SteadyClock::now();
  return dropped;
}

RtuExchange RtuMaster::receive(std::uint8_t slave, std::uint8_t function, std::chrono::nanoseconds timeout) {
  if (!is_open()) return {RtuOutcome::PortError, {}, settings_.serial.device + " is not open"};
  std::uint32_t seconds = 0;
  std::uint32_t micros = 0;
  split_timeout(timeout, seconds, micros);
  modbus_set_response_timeout(line_->context, seconds, micros);
  return receive_answer(slave, function, timeout);
}

void RtuMaster::tap(WireDirection direction, std::span<const std::uint8_t> bytes) const {
  if (monitor_ != nullptr) monitor_->record(direction, bytes);
}

void RtuMaster::tap_request(std::span<const std::uint8_t> slave_and_pdu) const {
  if (monitor_ == nullptr) return;
  // The frame as libmodbus sent it: slave, PDU, CRC.
  std::array<std::uint8_t, protocol::rtu::kMaxAduSize> frame{};
  std::copy(slave_and_pdu.begin(), slave_and_pdu.end(), frame.begin());
  const std::uint16_t crc = protocol::rtu::crc16(slave_and_pdu);
  frame[slave_and_pdu.size()] = static_cast<std::uint8_t>(crc);
  frame[slave_and_pdu.size() + 1] = static_cast<std::uint8_t>(crc >> 8);
  monitor_->record(WireDirection::ToServos, std::span(frame).first(slave_and_pdu.size() + 2));
}

int RtuMaster::native_handle() const { return line_->context == nullptr ? -1 : modbus_get_socket(line_->context); }

Expected<Ok> RtuMaster::send_frame(std::uint8_t slave, std::span<const std::uint8_t> pdu) {
  if (!is_open()) return unexpected(settings_.serial.device + " is not open");
  if (pdu.empty() || pdu.size() > protocol::rtu::kMaxPduSize) {
    throw std::invalid_argument("RtuMaster::send_frame: a PDU is 1 to 253 bytes, not " + std::to_string(pdu.size()));
  }
  Bytes frame;
  frame.reserve(pdu.size() + 1);
  frame.push_back(slave);
  frame.insert(frame.end(), pdu.begin(), pdu.end());
  if (modbus_send_raw_request(line_->context, frame.data(), static_cast<int>(frame.size())) < 0) {
    return unexpected("write to " + settings_.serial.device + ": " + modbus_strerror(errno));
  }
  line_->quiet_since = SteadyClock::now();
  return Ok{};
}

}  // namespace sms::gateway
