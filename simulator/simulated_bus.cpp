#include "simulator/simulated_bus.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/inotify.h>
#include <sys/ioctl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>
#include <random>
#include <stdexcept>
#include <system_error>
#include <thread>

#include <spdlog/spdlog.h>

#include "modbus_map/tables.h"
#include "protocol/feetech.h"
#include "protocol/modbus_rtu.h"
#include "protocol/stream_decoder.h"
#include "simulator/serial_line.h"
#include "simulator/state_file.h"
#include "simulator/virtual_servo.h"

namespace sms::simulator {

using protocol::BusProtocol;
using protocol::Bytes;

namespace {

// One character on the wire: start bit, 8 data bits, stop bit (docs/PROTOCOL.md §1).
constexpr double kBitsPerCharacter = 10.0;
// Modbus RTU inter-frame silence: 3.5 characters, fixed 1.75 ms above 19200 bit/s (docs/PROTOCOL.md §1.3).
constexpr std::uint32_t kFixedSilenceAbove = 19200;
constexpr auto kFixedSilence = std::chrono::microseconds(1750);
// A duplicate starts this many position units away from its twin, so their replies differ.
constexpr double kDuplicateSkew = 37.0;
// A host that stops reading: keep at most this much unsent, like a UART's buffer overflowing.
constexpr std::size_t kMaxUnsent = std::size_t{64} * 1024;
// The bus thread wakes at least this often; a wake-up this much later than asked is a hold of
// the machine's, kept (the last kHoldsKept) for the tests that ask (SimulatedBus::holds).
constexpr auto kHoldTick = std::chrono::milliseconds(5);
constexpr auto kHoldNoted = std::chrono::milliseconds(5);
constexpr std::size_t kHoldsKept = 256;

Clock::duration character_time(std::uint32_t baud) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(kBitsPerCharacter / baud));
}

std::string hex(std::span<const std::uint8_t> bytes) {
  static constexpr char kDigits[] = "0123456789ABCDEF";
  std::string text;
  text.reserve(bytes.size() * 3);
  for (const std::uint8_t byte : bytes) {
    if (!text.empty()) text += ' ';
    text += kDigits[byte >> 4];
    text += kDigits[byte & 0x0F];
  }
  return text;
}

void check_servos(const std::vector<ServoConfig>& servos) {
  if (servos.empty()) throw std::invalid_argument("a simulated bus needs at least one servo");
}

}  // namespace

BusOptions default_bus_options() {
  BusOptions options;
  for (std::uint8_t id = 1; id <= 6; ++id) {
    options.servos.push_back(ServoConfig{id, modbus_map::TableId::Sts, BusProtocol::Feetech, 1'000'000});
  }
  return options;
}

class SimulatedBus::Impl {
 public:
  explicit Impl(BusOptions options);
  ~Impl() { stop(); }

  void start();
  void stop();
  bool running() const { return thread_.joinable(); }
  std::string slave_path() const {
    std::lock_guard lock(mutex_);
    return slave_path_;
  }

  template <typename Action>
  bool for_id(std::uint8_t id, Action&& action) {
    std::lock_guard lock(mutex_);
    bool found = false;
    for (Slot& slot : slots_) {
      if (slot.servo->id() == id) {
        action(*slot.servo);
        found = true;
      }
    }
    save_state_if_dirty();
    return found;
  }
  VirtualServo* first_with_id(std::uint8_t id) {
    for (Slot& slot : slots_) {
      if (slot.servo->id() == id) return slot.servo.get();
    }
    return nullptr;
  }

  void add_duplicate(std::uint8_t id);

  mutable std::mutex mutex_;
  BusOptions options_;
  double drop_probability_ = 0;
  double corrupt_probability_ = 0;
  unsigned corrupt_next_ = 0;
  unsigned drop_next_ = 0;
  bool timing_ = true;
  BusStats stats_;
  std::deque<Hold> holds_;  // the last kHoldsKept
  FrameObserver observer_;

  struct Slot {
    std::unique_ptr<VirtualServo> servo;
    std::optional<std::size_t> persisted_as;  // slot number in the state file; none for duplicates
  };
  std::vector<Slot> slots_;

 private:
  struct Reply {
    std::size_t rank;  // SYNC READ: position of the ID in the list; else 0
    VirtualServo* servo;
    Bytes bytes;
  };
  struct ScheduledReply {
    Clock::time_point due;
    Clock::time_point wire_start;
    Clock::time_point wire_end;
    Bytes bytes;
    const VirtualServo* servo;  // who sends it (a collision's: the earlier sender)
  };
  // When each servo has finished sending what it already answered, and when its last reply is
  // written: a servo answers one request after the other, in turn, never over itself.
  struct Answering {
    Clock::time_point wire_end{};
    Clock::time_point due{};
  };

  void open_line();
  void close_line();
  void run();
  void on_bytes(std::span<const std::uint8_t> bytes, Clock::time_point now);
  void on_packet(const protocol::PacketFormat& format, const protocol::DecodeEvent& event, std::uint32_t speed,
                 Clock::time_point request_end, Clock::time_point now);
  void on_modbus(const protocol::rtu::RequestDecoder::Event& event, std::uint32_t speed, Clock::time_point request_end,
                 Clock::time_point now);
  void schedule(std::vector<Reply> replies, std::uint32_t speed, Clock::time_point request_end, Clock::time_point now);
  void add_scheduled(ScheduledReply reply, Clock::duration character);
  bool listens(BusProtocol protocol, std::uint32_t speed) const;
  void flush_due(Clock::time_point now);
  void write_out();
  std::optional<Clock::time_point> next_deadline() const;
  void on_hosts_opening_or_closing();
  Clock::duration rtu_silence() const;
  // The servo's t3.5 between frames: 3.5 characters at every rate (no fixed 1.75 ms).
  Clock::duration rtu_interframe() const;
  void save_state_if_dirty();
  std::uint32_t current_speed() const;

  std::thread thread_;
  bool stopping_ = false;
  int line_fd_ = -1;
  int slave_fd_ = -1;  // held open so a host closing its end never hangs the pty up
  int wake_fd_ = -1;
  // A pty's hosts, as a real adapter's last close would: the exclusive use a host claimed
  // (TIOCEXCL) ends when no host has the pty open any more. Otherwise it would outlive a host
  // that died without giving it up (SIGKILL, a crash), since our slave_fd_ keeps the tty alive,
  // and every later open by a user other than root would fail with EBUSY.
  int hosts_fd_ = -1;  // inotify: the hosts' opens and closes of the pty slave
  int hosts_open_ = 0;
  std::string slave_path_;
  bool link_created_ = false;
  std::mt19937 dice_;

  protocol::StreamDecoder feetech_decoder_{protocol::kFeetechFormat};
  protocol::StreamDecoder d55d_decoder_{protocol::kD55dFormat};
  protocol::rtu::RequestDecoder rtu_decoder_;
  std::uint32_t rtu_speed_ = 0;
  bool rtu_merging_ = false;  // a request came too early: ignored until the line is silent
  Clock::time_point last_received_{};
  Clock::time_point wire_free_{};  // when the (virtual) wire is next idle
  std::vector<ScheduledReply> scheduled_;
  std::map<const VirtualServo*, Answering> answering_;
  Bytes unsent_;
};

SimulatedBus::Impl::Impl(BusOptions options) : options_(std::move(options)), timing_(options_.timing) {
  check_servos(options_.servos);
  dice_.seed(options_.seed != 0 ? options_.seed : std::random_device{}());
  const Clock::time_point now = Clock::now();
  for (std::size_t index = 0; index < options_.servos.size(); ++index) {
    slots_.push_back(Slot{std::make_unique<VirtualServo>(options_.servos[index], now, options_.reboot_time), index});
  }
}

void SimulatedBus::Impl::start() {
  if (running()) return;
  {
    std::lock_guard lock(mutex_);
    if (!options_.state_file.empty()) {
      const PersistedState state = load_state_file(options_.state_file);
      const Clock::time_point now = Clock::now();
      for (Slot& slot : slots_) {
        if (!slot.persisted_as) continue;
        const auto found = state.find(*slot.persisted_as);
        if (found == state.end()) continue;
        if (found->second.table != slot.servo->table().name) {
          spdlog::warn("sms-sim: {} slot {} holds a {} servo, this one is {}; not loaded", options_.state_file,
                       *slot.persisted_as, found->second.table, slot.servo->table().name);
          continue;
        }
        for (const auto& name : slot.servo->load_persisted(found->second.eeprom, found->second.backup, now)) {
          spdlog::warn("sms-sim: {} slot {}: no EEPROM field '{}' in table {}; ignored", options_.state_file,
                       *slot.persisted_as, name, slot.servo->table().name);
        }
      }
    }
    open_line();
    stopping_ = false;
  }
  thread_ = std::thread([this] { run(); });
}

void SimulatedBus::Impl::stop() {
  if (!running()) return;
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  const std::uint64_t one = 1;
  [[maybe_unused]] const auto written = ::write(wake_fd_, &one, sizeof one);
  thread_.join();
  std::lock_guard lock(mutex_);
  close_line();
}

void SimulatedBus::Impl::open_line() {
  const std::uint32_t initial_baud = slots_.front().servo->baud();
  const auto fail = [](const std::string& what) { throw std::system_error(errno, std::generic_category(), what); };
  if (!options_.device.empty()) {
    line_fd_ = ::open(options_.device.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (line_fd_ < 0) fail("cannot open serial device " + options_.device);
    configure_raw_serial(line_fd_, initial_baud);
    slave_path_ = options_.device;
  } else {
    line_fd_ = ::posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (line_fd_ < 0) fail("cannot create a pseudo-terminal (is /dev/ptmx available?)");
    if (::grantpt(line_fd_) != 0 || ::unlockpt(line_fd_) != 0) fail("cannot unlock the pseudo-terminal");
    std::array<char, 128> name{};
    if (::ptsname_r(line_fd_, name.data(), name.size()) != 0) fail("cannot name the pseudo-terminal");
    slave_path_ = name.data();
    slave_fd_ = ::open(slave_path_.c_str(), O_RDWR | O_NOCTTY | O_CLOEXEC);
    if (slave_fd_ < 0) fail("cannot open the pty slave " + slave_path_);
    configure_raw_serial(slave_fd_, initial_baud);
    // From here on every open and close is a host's. Without inotify the pty still works; only a
    // host that dies holding it exclusively leaves it busy.
    hosts_fd_ = ::inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
    if (hosts_fd_ >= 0 && ::inotify_add_watch(hosts_fd_, slave_path_.c_str(), IN_OPEN | IN_CLOSE) < 0) {
      ::close(hosts_fd_);
      hosts_fd_ = -1;
    }
    if (hosts_fd_ < 0) {
      spdlog::warn(
          "sms-sim: cannot watch who opens {} ({}): a host killed while it holds it exclusively leaves it "
          "busy until sms-sim restarts",
          slave_path_, std::strerror(errno));
    }
    hosts_open_ = 0;
  }
  if (!options_.link.empty()) {
    struct stat existing {};
    if (::lstat(options_.link.c_str(), &existing) == 0) {
      if (!S_ISLNK(existing.st_mode)) {
        throw std::runtime_error("--link " + options_.link + " exists and is not a symlink; not replacing it");
      }
      ::unlink(options_.link.c_str());
    }
    if (::symlink(slave_path_.c_str(), options_.link.c_str()) != 0) {
      fail("cannot create symlink " + options_.link + " -> " + slave_path_);
    }
    link_created_ = true;
  }
  wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) fail("cannot create an eventfd");
  wire_free_ = Clock::now();
}

void SimulatedBus::Impl::close_line() {
  for (int* fd : {&line_fd_, &slave_fd_, &wake_fd_, &hosts_fd_}) {
    if (*fd >= 0) ::close(*fd);
    *fd = -1;
  }
  if (link_created_) ::unlink(options_.link.c_str());
  link_created_ = false;
  slave_path_.clear();
  scheduled_.clear();
  unsent_.clear();
  feetech_decoder_.reset();
  d55d_decoder_.reset();
  rtu_decoder_.reset();
}

std::uint32_t SimulatedBus::Impl::current_speed() const {
  try {
    // A pty left without a rate (an emulator without termios2) carries the servos' own rate: the
    // rate a host set cannot be told there, so a wrong one goes unnoticed under emulation only.
    const std::uint32_t speed = line_speed(line_fd_);
    return speed != 0 ? speed : slots_.front().servo->baud();
  } catch (const std::system_error&) {
    return slots_.front().servo->baud();
  }
}

Clock::duration SimulatedBus::Impl::rtu_interframe() const {
  return character_time(std::max<std::uint32_t>(rtu_speed_, 1)) * 7 / 2;
}

Clock::duration SimulatedBus::Impl::rtu_silence() const {
  if (rtu_speed_ > kFixedSilenceAbove) return kFixedSilence;
  return character_time(std::max<std::uint32_t>(rtu_speed_, 1)) * 7 / 2;
}

std::optional<Clock::time_point> SimulatedBus::Impl::next_deadline() const {
  std::optional<Clock::time_point> deadline;
  for (const ScheduledReply& reply : scheduled_) {
    if (!deadline || reply.due < *deadline) deadline = reply.due;
  }
  if (rtu_decoder_.buffered() > 0) {
    const Clock::time_point silence = last_received_ + rtu_silence();
    if (!deadline || silence < *deadline) deadline = silence;
  }
  return deadline;
}

void SimulatedBus::Impl::run() {
  std::array<std::uint8_t, 4096> buffer{};
  for (;;) {
    timespec timeout{};
    short line_events = POLLIN;
    Clock::time_point wake_by;
    {
      std::lock_guard lock(mutex_);
      if (stopping_) return;
      // At the next deadline, and every kHoldTick at the latest: a wake-up later than asked for
      // is a hold of the machine's (holds()).
      const Clock::time_point now = Clock::now();
      wake_by = now + kHoldTick;
      if (const auto deadline = next_deadline()) wake_by = std::clamp(*deadline, now, wake_by);
      const auto nanos = std::chrono::duration_cast<std::chrono::nanoseconds>(wake_by - now).count();
      timeout.tv_sec = static_cast<time_t>(nanos / 1'000'000'000);
      timeout.tv_nsec = static_cast<long>(nanos % 1'000'000'000);
      if (!unsent_.empty()) line_events |= POLLOUT;
    }
    std::array<pollfd, 3> fds{{{line_fd_, line_events, 0}, {wake_fd_, POLLIN, 0}, {hosts_fd_, POLLIN, 0}}};
    const int ready = ::ppoll(fds.data(), fds.size(), &timeout, nullptr);
    if (const Clock::time_point woke = Clock::now(); woke - wake_by >= kHoldNoted) {
      std::lock_guard lock(mutex_);
      holds_.push_back(Hold{woke, woke - wake_by});
      if (holds_.size() > kHoldsKept) holds_.pop_front();
    }
    if (ready < 0 && errno != EINTR) {
      spdlog::error("sms-sim: poll on {} failed: {}", slave_path_, std::strerror(errno));
      return;
    }
    if ((fds[1].revents & POLLIN) != 0) {
      std::uint64_t count = 0;
      [[maybe_unused]] const auto drained = ::read(wake_fd_, &count, sizeof count);
    }
    if ((fds[2].revents & POLLIN) != 0) on_hosts_opening_or_closing();
    if ((fds[0].revents & POLLIN) != 0) {
      const ssize_t received = ::read(line_fd_, buffer.data(), buffer.size());
      const Clock::time_point now = Clock::now();
      if (received > 0) {
        std::lock_guard lock(mutex_);
        on_bytes(std::span<const std::uint8_t>(buffer.data(), static_cast<std::size_t>(received)), now);
      } else if (received < 0 && errno != EAGAIN && errno != EINTR) {
        spdlog::error("sms-sim: read from {} failed: {}", slave_path_, std::strerror(errno));
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
      }
    }
    if ((fds[0].revents & (POLLERR | POLLHUP)) != 0 && (fds[0].revents & POLLIN) == 0) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));  // device gone; do not spin
    }
    std::lock_guard lock(mutex_);
    const Clock::time_point now = Clock::now();
    if (rtu_decoder_.buffered() > 0 && now >= last_received_ + rtu_silence()) {
      if (const auto event = rtu_decoder_.end_of_frame()) on_modbus(*event, rtu_speed_, wire_free_, now);
    }
    flush_due(now);
  }
}

void SimulatedBus::Impl::on_hosts_opening_or_closing() {
  // Counted over every event read at once: a host that died and one that opened right after
  // (root may, while the flag is still up) leave the count at one and the new host's claim stands.
  alignas(inotify_event) std::array<char, 4096> events{};
  for (;;) {
    const ssize_t length = ::read(hosts_fd_, events.data(), events.size());
    if (length <= 0) break;
    for (ssize_t at = 0; at < length;) {
      inotify_event event{};
      std::memcpy(&event, events.data() + at, sizeof event);
      if ((event.mask & IN_OPEN) != 0) ++hosts_open_;
      if ((event.mask & IN_CLOSE) != 0) hosts_open_ = std::max(hosts_open_ - 1, 0);
      at += static_cast<ssize_t>(sizeof event + event.len);
    }
  }
  // No-op unless a host left its exclusive claim behind. (The descriptors change only while
  // this thread is not running.)
  if (hosts_open_ == 0) (void)::ioctl(slave_fd_, TIOCNXCL);
}

bool SimulatedBus::Impl::listens(BusProtocol protocol, std::uint32_t speed) const {
  return std::any_of(slots_.begin(), slots_.end(), [&](const Slot& slot) {
    return slot.servo->protocol() == protocol && slot.servo->baud() == speed;
  });
}

void SimulatedBus::Impl::on_bytes(std::span<const std::uint8_t> bytes, Clock::time_point now) {
  const std::uint32_t speed = current_speed();
  if (speed == 0) return;
  // The request occupies the wire from when it arrived (or when the wire became free). Without
  // timing the host may outrun the wire; the virtual wire then restarts at each arrival so it
  // never runs ahead of real time.
  const Clock::time_point previous_frame_end = wire_free_;
  const Clock::time_point wire_start = timing_ ? std::max(wire_free_, now) : now;
  wire_free_ = wire_start + character_time(speed) * static_cast<long>(bytes.size());
  const Clock::time_point request_end = wire_free_;
  if (spdlog::should_log(spdlog::level::debug)) {
    spdlog::debug("sms-sim rx @{} baud: {}", speed, hex(bytes));
  }

  // A servo at another rate sees only framing errors: its decoder forgets what it had.
  bool packet_frame = false;
  for (const auto& [protocol, decoder] :
       {std::pair{BusProtocol::Feetech, &feetech_decoder_}, std::pair{BusProtocol::D55d, &d55d_decoder_}}) {
    if (!listens(protocol, speed)) {
      decoder->reset();
      continue;
    }
    decoder->feed(bytes);
    const protocol::PacketFormat& format =
        protocol == BusProtocol::Feetech ? protocol::kFeetechFormat : protocol::kD55dFormat;
    while (const auto event = decoder->next()) {
      packet_frame = packet_frame || event->kind == protocol::DecodeEvent::Kind::Frame;
      on_packet(format, *event, speed, request_end, now);
    }
  }
  if (!listens(BusProtocol::ModbusRtu, speed)) {
    rtu_decoder_.reset();
  } else {
    if (rtu_speed_ != speed) rtu_decoder_.reset();
    rtu_speed_ = speed;
    // The silence that ends a Modbus frame may have passed before the poll loop looked.
    if (rtu_decoder_.buffered() > 0 && now >= last_received_ + rtu_silence()) {
      if (const auto event = rtu_decoder_.end_of_frame()) on_modbus(*event, speed, request_end, now);
    }
    const bool silence_passed = now >= last_received_ + rtu_silence();
    last_received_ = now;
    if (rtu_merging_ && silence_passed) rtu_merging_ = false;
    // A slave's own t3.5: a request that starts before the line was silent for 3.5
    // characters after the previous frame (a request, or a servo's reply) is heard as the tail of
    // that frame, fails its CRC and is ignored — until the line falls silent again.
    if (timing_ && !rtu_merging_ && rtu_decoder_.buffered() == 0 && now < previous_frame_end + rtu_interframe()) {
      rtu_merging_ = true;
      ++stats_.merged_requests;
      spdlog::debug(
          "sms-sim: modbus-rtu request {} us after the previous frame, less than 3.5 characters: "
          "merged with it and ignored",
          std::chrono::duration_cast<std::chrono::microseconds>(now - previous_frame_end).count());
    }
    if (rtu_merging_ || packet_frame) {
      // Merging: the rest of a request glued to the one before is ignored too. A packet frame:
      // another protocol's frame on a mixed bus is noise to the Modbus slaves that ends
      // whatever they were collecting. Without wire timing the host may follow it by less than
      // the 3.5-character silence, which would otherwise glue it to the next Modbus request.
      rtu_decoder_.reset();
    } else {
      rtu_decoder_.feed(bytes);
      while (const auto event = rtu_decoder_.next()) {
        on_modbus(*event, speed, request_end, now);
        if (timing_ && event->kind == protocol::rtu::RequestDecoder::Event::Kind::Frame &&
            rtu_decoder_.buffered() > 0) {
          // The next request followed this one without any silence: merged with it, ignored.
          rtu_merging_ = true;
          ++stats_.merged_requests;
          rtu_decoder_.reset();
          break;
        }
      }
    }
  }
  save_state_if_dirty();
  flush_due(now);
}

void SimulatedBus::Impl::on_packet(const protocol::PacketFormat& format, const protocol::DecodeEvent& event,
                                   std::uint32_t speed, Clock::time_point request_end, Clock::time_point now) {
  const BusProtocol protocol = &format == &protocol::kFeetechFormat ? BusProtocol::Feetech : BusProtocol::D55d;
  const protocol::Packet& request = event.packet;
  if (event.kind != protocol::DecodeEvent::Kind::Frame) {
    if (event.kind == protocol::DecodeEvent::Kind::ChecksumError) {
      ++stats_.checksum_errors;
      for (Slot& slot : slots_) {
        VirtualServo& servo = *slot.servo;
        if (servo.protocol() == protocol && servo.baud() == speed && servo.id() == request.id) {
          servo.note_checksum_error();
        }
      }
    }
    return;
  }
  ++stats_.requests;
  if (observer_) observer_(ReceivedFrame{now, request_end, protocol, request.id, request.code, request.params});
  std::vector<std::uint8_t> sync_read_ids;
  if (protocol == BusProtocol::Feetech && request.code == protocol::feetech::kSyncRead) {
    if (const auto sync = protocol::feetech::parse_sync_read(request.params)) sync_read_ids = sync->ids;
  }
  std::vector<Reply> replies;
  for (Slot& slot : slots_) {
    VirtualServo& servo = *slot.servo;
    if (servo.protocol() != protocol || servo.baud() != speed || !servo.listening(now)) continue;
    const std::uint8_t id = servo.id();
    if (request.id != protocol::kBroadcastId && request.id != id) continue;
    const auto reply = servo.handle_packet(request, now);
    if (!reply) continue;
    const auto listed = std::find(sync_read_ids.begin(), sync_read_ids.end(), id);
    const std::size_t rank =
        listed == sync_read_ids.end() ? 0 : static_cast<std::size_t>(listed - sync_read_ids.begin());
    replies.push_back(Reply{rank, &servo, protocol::encode(format, *reply)});
  }
  schedule(std::move(replies), speed, request_end, now);
}

void SimulatedBus::Impl::on_modbus(const protocol::rtu::RequestDecoder::Event& event, std::uint32_t speed,
                                   Clock::time_point request_end, Clock::time_point now) {
  if (event.kind != protocol::rtu::RequestDecoder::Event::Kind::Frame) {
    ++stats_.checksum_errors;  // a slave ignores a frame whose CRC fails
    return;
  }
  ++stats_.requests;
  if (observer_ && !event.adu.pdu.empty()) {
    observer_(ReceivedFrame{now, request_end, BusProtocol::ModbusRtu, event.adu.slave, event.adu.pdu.front(),
                            Bytes(event.adu.pdu.begin() + 1, event.adu.pdu.end())});
  }
  std::vector<Reply> replies;
  for (Slot& slot : slots_) {
    VirtualServo& servo = *slot.servo;
    if (servo.protocol() != BusProtocol::ModbusRtu || servo.baud() != speed || !servo.listening(now)) continue;
    if (event.adu.slave != 0 && event.adu.slave != servo.id()) continue;
    if (auto reply = servo.handle_modbus(event.adu, now)) replies.push_back(Reply{0, &servo, std::move(*reply)});
  }
  schedule(std::move(replies), speed, request_end, now);
}

void SimulatedBus::Impl::schedule(std::vector<Reply> replies, std::uint32_t speed, Clock::time_point request_end,
                                  Clock::time_point now) {
  if (replies.empty()) return;
  std::stable_sort(replies.begin(), replies.end(), [](const Reply& a, const Reply& b) { return a.rank < b.rank; });
  const Clock::duration character = character_time(speed);
  std::uniform_real_distribution<double> chance(0.0, 1.0);
  // Each SYNC READ answer starts after the previous one ended, plus its own return delay;
  // replies of the same rank (same ID twice) start together and collide.
  Clock::time_point previous_end = request_end;
  Clock::time_point group_end = request_end;
  std::size_t group_rank = replies.front().rank;
  for (Reply& reply : replies) {
    if (reply.rank != group_rank) {
      previous_end = group_end;
      group_rank = reply.rank;
    }
    // Two requests read at once (sent back to back): the servo answers the second after the first.
    Answering& answering = answering_[reply.servo];
    const Clock::time_point start = std::max(previous_end + reply.servo->return_delay(), answering.wire_end);
    const Clock::time_point end = start + character * static_cast<long>(reply.bytes.size());
    answering.wire_end = end;
    group_end = std::max(group_end, end);
    if (drop_next_ > 0 || (drop_probability_ > 0 && chance(dice_) < drop_probability_)) {
      if (drop_next_ > 0) --drop_next_;
      ++stats_.dropped;
      continue;
    }
    bool corrupt = reply.servo->garbled();
    if (!corrupt && corrupt_next_ > 0) {
      --corrupt_next_;
      corrupt = true;
    }
    if (!corrupt && corrupt_probability_ > 0) corrupt = chance(dice_) < corrupt_probability_;
    if (corrupt) {
      std::uniform_int_distribution<std::size_t> position(0, reply.bytes.size() - 1);
      std::uniform_int_distribution<int> mask(1, 255);
      reply.bytes[position(dice_)] ^= static_cast<std::uint8_t>(mask(dice_));
      ++stats_.corrupted;
    }
    // A late servo stays in order: a reply never overtakes the one it sent before.
    const Clock::time_point due = std::max((timing_ ? end : now) + reply.servo->extra_delay(), answering.due);
    answering.due = due;
    add_scheduled(ScheduledReply{due, start, end, std::move(reply.bytes), reply.servo}, character);
  }
  wire_free_ = std::max(wire_free_, group_end);
  flush_due(now);
}

void SimulatedBus::Impl::add_scheduled(ScheduledReply reply, Clock::duration character) {
  for (ScheduledReply& other : scheduled_) {
    if (!(reply.wire_start < other.wire_end && other.wire_start < reply.wire_end)) continue;
    if (other.servo == reply.servo) continue;  // only two different servos collide
    // Two transmitters at once: on the idle-high line a 0 bit wins, so overlapping
    // characters AND together; each one's own characters fill the rest.
    ScheduledReply& earlier = reply.wire_start < other.wire_start ? reply : other;
    ScheduledReply& later = reply.wire_start < other.wire_start ? other : reply;
    const auto offset = static_cast<std::size_t>(
        std::max<long>(0, static_cast<long>((later.wire_start - earlier.wire_start) / character)));
    Bytes merged = earlier.bytes;
    merged.resize(std::max(merged.size(), offset + later.bytes.size()), 0xFF);
    for (std::size_t index = 0; index < later.bytes.size(); ++index) {
      merged[offset + index] &= later.bytes[index];
    }
    other = ScheduledReply{std::max(reply.due, other.due), earlier.wire_start, std::max(reply.wire_end, other.wire_end),
                           std::move(merged), earlier.servo};
    ++stats_.collisions;
    return;
  }
  scheduled_.push_back(std::move(reply));
}

void SimulatedBus::Impl::flush_due(Clock::time_point now) {
  std::stable_sort(scheduled_.begin(), scheduled_.end(),
                   [](const ScheduledReply& a, const ScheduledReply& b) { return a.due < b.due; });
  std::size_t sent = 0;
  while (sent < scheduled_.size() && scheduled_[sent].due <= now) {
    const Bytes& bytes = scheduled_[sent].bytes;
    if (spdlog::should_log(spdlog::level::debug)) spdlog::debug("sms-sim tx: {}", hex(bytes));
    if (unsent_.size() + bytes.size() <= kMaxUnsent) unsent_.insert(unsent_.end(), bytes.begin(), bytes.end());
    ++stats_.replies;
    ++sent;
  }
  scheduled_.erase(scheduled_.begin(), scheduled_.begin() + static_cast<long>(sent));
  write_out();
}

void SimulatedBus::Impl::write_out() {
  while (!unsent_.empty() && line_fd_ >= 0) {
    const ssize_t written = ::write(line_fd_, unsent_.data(), unsent_.size());
    if (written <= 0) return;  // EAGAIN: the poll loop waits for POLLOUT
    unsent_.erase(unsent_.begin(), unsent_.begin() + written);
  }
}

void SimulatedBus::Impl::save_state_if_dirty() {
  bool dirty = false;
  for (Slot& slot : slots_) dirty = slot.servo->take_persist_dirty() || dirty;
  if (!dirty || options_.state_file.empty()) return;
  PersistedState state;
  for (const Slot& slot : slots_) {
    if (!slot.persisted_as) continue;
    state[*slot.persisted_as] = PersistedServo{std::string(slot.servo->table().name), slot.servo->persisted_eeprom(),
                                               slot.servo->backup_eeprom()};
  }
  try {
    save_state_file(options_.state_file, state);
  } catch (const std::exception& error) {
    spdlog::error("sms-sim: {}", error.what());
  }
}

void SimulatedBus::Impl::add_duplicate(std::uint8_t id) {
  std::lock_guard lock(mutex_);
  const VirtualServo* twin = first_with_id(id);
  if (twin == nullptr) {
    throw std::invalid_argument("cannot duplicate servo " + std::to_string(id) + ": no servo has that ID");
  }
  const ServoConfig config{id, twin->table().id, twin->protocol(), twin->baud()};
  slots_.push_back(
      Slot{std::make_unique<VirtualServo>(config, Clock::now(), options_.reboot_time, kDuplicateSkew), std::nullopt});
}

// --- SimulatedBus -----------------------------------------------------------------------

SimulatedBus::SimulatedBus(BusOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {}
SimulatedBus::~SimulatedBus() = default;

void SimulatedBus::start() { impl_->start(); }
void SimulatedBus::stop() { impl_->stop(); }
bool SimulatedBus::running() const { return impl_->running(); }
std::string SimulatedBus::slave_path() const { return impl_->slave_path(); }

void SimulatedBus::set_offline(std::uint8_t id, bool offline) {
  impl_->for_id(id, [offline](VirtualServo& servo) { servo.set_offline(offline); });
}

void SimulatedBus::set_drop_probability(double probability) {
  std::lock_guard lock(impl_->mutex_);
  impl_->drop_probability_ = std::clamp(probability, 0.0, 1.0);
}

void SimulatedBus::set_corrupt_probability(double probability) {
  std::lock_guard lock(impl_->mutex_);
  impl_->corrupt_probability_ = std::clamp(probability, 0.0, 1.0);
}

void SimulatedBus::corrupt_next_replies(unsigned count) {
  std::lock_guard lock(impl_->mutex_);
  impl_->corrupt_next_ += count;
}

void SimulatedBus::drop_next_replies(unsigned count) {
  std::lock_guard lock(impl_->mutex_);
  impl_->drop_next_ += count;
}

void SimulatedBus::set_garbled(std::uint8_t id, bool garbled) {
  impl_->for_id(id, [garbled](VirtualServo& servo) { servo.set_garbled(garbled); });
}

void SimulatedBus::set_reply_delay(std::uint8_t id, std::chrono::milliseconds extra) {
  impl_->for_id(id, [extra](VirtualServo& servo) { servo.set_extra_delay(extra); });
}

void SimulatedBus::set_error_bits(std::uint8_t id, std::uint8_t bits) {
  const Clock::time_point now = Clock::now();
  impl_->for_id(id, [bits, now](VirtualServo& servo) { servo.set_error_bits(bits, now); });
}

void SimulatedBus::add_duplicate(std::uint8_t id) { impl_->add_duplicate(id); }

void SimulatedBus::set_timing(bool enabled) {
  std::lock_guard lock(impl_->mutex_);
  impl_->timing_ = enabled;
}

std::optional<Bytes> SimulatedBus::read_memory(std::uint8_t id, std::uint16_t address, std::uint16_t count) {
  std::lock_guard lock(impl_->mutex_);
  VirtualServo* servo = impl_->first_with_id(id);
  if (servo == nullptr || !servo->memory().contains(address, count)) return std::nullopt;
  servo->update(Clock::now());
  const auto bytes = servo->memory().wire(address, count);
  return Bytes(bytes.begin(), bytes.end());
}

bool SimulatedBus::write_memory(std::uint8_t id, std::uint16_t address, std::span<const std::uint8_t> bytes) {
  const Clock::time_point now = Clock::now();
  bool written = false;
  const bool found =
      impl_->for_id(id, [&](VirtualServo& servo) { written = servo.write_raw(address, bytes, now) || written; });
  return found && written;
}

std::optional<std::int32_t> SimulatedBus::read_field(std::uint8_t id, std::string_view field_name) {
  std::lock_guard lock(impl_->mutex_);
  VirtualServo* servo = impl_->first_with_id(id);
  if (servo == nullptr) return std::nullopt;
  const modbus_map::FieldSpec* spec = modbus_map::field_by_name(servo->table(), field_name);
  if (spec == nullptr) return std::nullopt;
  servo->update(Clock::now());
  return servo->memory().value(*spec);
}

std::vector<ServoSummary> SimulatedBus::servos() const {
  std::lock_guard lock(impl_->mutex_);
  const Clock::time_point now = Clock::now();
  std::vector<ServoSummary> summaries;
  for (const Impl::Slot& slot : impl_->slots_) {
    slot.servo->update(now);
    ServoSummary summary = slot.servo->summary();
    summary.duplicate = !slot.persisted_as.has_value();
    summaries.push_back(summary);
  }
  return summaries;
}

BusStats SimulatedBus::stats() const {
  std::lock_guard lock(impl_->mutex_);
  return impl_->stats_;
}

std::vector<Hold> SimulatedBus::holds() const {
  std::lock_guard lock(impl_->mutex_);
  return {impl_->holds_.begin(), impl_->holds_.end()};
}

void SimulatedBus::set_frame_observer(FrameObserver observer) {
  std::lock_guard lock(impl_->mutex_);
  impl_->observer_ = std::move(observer);
}

}  // namespace sms::simulator
