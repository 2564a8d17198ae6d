#include "gateway/net/door.h"

#include <algorithm>
#include <list>
#include <map>
#include <mutex>

#include <spdlog/spdlog.h>
#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>

namespace sms::gateway {

namespace asio = boost::asio;
using Clock = std::chrono::steady_clock;

DoorLimitNames fixed_limit_names(std::string_view whose) {
  const std::string owner = std::string(whose) + "'s ";
  return {owner + "connection limit", owner + "limit of waiting connections", owner + "limit per client address",
          owner + "first-request deadline"};
}

std::string duration_text(std::chrono::milliseconds duration) {
  if (duration.count() % 1000 == 0) return std::to_string(duration.count() / 1000) + " s";
  return std::to_string(duration.count()) + " ms";
}

namespace {

// A flood of connections is what makes the door close many: the first of a kind is logged, the
// rest of each 10 s are counted and said with the next line.
class FloodLog {
 public:
  template <typename... Args>
  void warn(spdlog::format_string_t<Args...> format, Args&&... args) {
    const auto now = Clock::now();
    if (logged_ && now - last_ < kInterval) {
      ++held_back_;
      return;
    }
    const std::string line = fmt::format(format, std::forward<Args>(args)...);
    if (held_back_ == 0) {
      spdlog::warn("{}", line);
    } else {
      spdlog::warn("{}; {} more since the last line", line, held_back_);
    }
    logged_ = true;
    last_ = now;
    held_back_ = 0;
  }

 private:
  static constexpr std::chrono::seconds kInterval{10};
  Clock::time_point last_{};
  bool logged_ = false;
  std::uint64_t held_back_ = 0;
};

}  // namespace

struct Door::State : std::enable_shared_from_this<Door::State> {
  struct Entry {
    Ticket ticket = 0;
    std::string address;
    std::weak_ptr<DoorGuest> guest;
    Clock::time_point admitted_at;
    bool heard = false;
    bool trusted = false;
  };

  State(asio::io_context& io, DoorSettings door_settings) : settings(std::move(door_settings)), timer(io) {}

  const DoorSettings settings;
  asio::steady_timer timer;
  bool closed = false;
  std::list<Entry> entries;  // oldest first
  Ticket next_ticket = 1;
  bool full_logged = false;
  FloodLog eviction_log;
  FloodLog deadline_log;
  Clock::time_point armed_for = Clock::time_point::max();

  mutable std::mutex stats_mutex;  // stats() is read from other threads (/metrics)
  DoorStats stats;

  std::list<Entry>::iterator find(Ticket ticket) {
    return std::find_if(entries.begin(), entries.end(), [&](const Entry& e) { return e.ticket == ticket; });
  }

  void count(DoorClose why) {
    std::lock_guard lock(stats_mutex);
    ++stats.closed[static_cast<std::size_t>(why)];
  }

  void publish_sizes() {
    const auto served = static_cast<std::size_t>(
        std::count_if(entries.begin(), entries.end(), [](const Entry& e) { return e.trusted; }));
    std::lock_guard lock(stats_mutex);
    stats.served = served;
    stats.waiting = entries.size() - served;
  }

  std::size_t served_count() const {
    return static_cast<std::size_t>(
        std::count_if(entries.begin(), entries.end(), [](const Entry& e) { return e.trusted; }));
  }

  void log_full(const std::string& peer) {
    if (full_logged) return;
    full_logged = true;
    spdlog::warn(
        "{}: refusing connection from {}: {} connections served, the limit ({}); further refusals are counted, not "
        "logged",
        settings.log_name, peer, settings.limits.max_served, settings.limit_names.max_served);
  }

  // Closes a waiting connection to make room: from `only` when given (its address's budget is
  // full), else from the address holding the most waiting connections (a flood from a few
  // addresses makes room from its own, never from a client that came alone); within those, the
  // oldest silent one, else the oldest. Silent connections anywhere go before any that spoke.
  void evict_for(const std::string& newcomer, const std::string* only, const std::string& limit) {
    std::map<std::string_view, std::size_t> waiting_from;
    for (const auto& entry : entries) {
      if (!entry.trusted) ++waiting_from[entry.address];
    }
    std::size_t most = 0;
    for (const auto& [address, count] : waiting_from) most = std::max(most, count);
    // Entries are in arrival order: the first found is the oldest. Among addresses that hold
    // equally many, the one whose connection waited longest gives way, never the one that sorts
    // first (a flood from many addresses, one each, churns among itself, not at 127.0.0.1's cost).
    Entry* oldest_silent = nullptr;
    Entry* oldest_of_greediest = nullptr;
    for (auto& entry : entries) {
      if (entry.trusted || (only != nullptr && entry.address != *only)) continue;
      const auto guest = entry.guest.lock();
      if (oldest_silent == nullptr && (!guest || guest->silent())) oldest_silent = &entry;
      if (oldest_of_greediest == nullptr && (only != nullptr || waiting_from[entry.address] == most)) {
        oldest_of_greediest = &entry;
      }
    }
    Entry* victim = oldest_silent != nullptr ? oldest_silent : oldest_of_greediest;
    if (victim == nullptr) return;
    const Ticket ticket = victim->ticket;
    const auto guest = victim->guest.lock();
    count(DoorClose::Evicted);
    eviction_log.warn(
        "{}: closing {} ({}waiting for a {}) to make room for a new connection from {} ({} reached) [evicted]",
        settings.log_name, guest ? guest->peer() : victim->address, oldest_silent != nullptr ? "silent so far, " : "",
        settings.first_request, newcomer, limit);
    forget(ticket);
    if (settings.on_close) settings.on_close(DoorClose::Evicted);
    if (guest) guest->close_by_door();
  }

  void forget(Ticket ticket) {
    const auto found = find(ticket);
    if (found == entries.end()) return;
    entries.erase(found);
    if (served_count() < settings.limits.max_served) full_logged = false;
    publish_sizes();
  }

  // The deadline of the oldest connection still without its first request.
  void arm() {
    if (closed || settings.limits.first_request_timeout.count() <= 0) return;
    const auto oldest = std::find_if(entries.begin(), entries.end(), [](const Entry& e) { return !e.heard; });
    if (oldest == entries.end()) return;
    const auto deadline = oldest->admitted_at + settings.limits.first_request_timeout;
    if (deadline == armed_for) return;
    armed_for = deadline;
    timer.expires_at(deadline);
    timer.async_wait([weak = weak_from_this()](const boost::system::error_code& error) {
      if (error) return;
      if (const auto state = weak.lock()) state->expire();
    });
  }

  void expire() {
    armed_for = Clock::time_point::max();
    if (closed) return;
    const auto now = Clock::now();
    std::vector<std::shared_ptr<DoorGuest>> late;
    for (auto it = entries.begin(); it != entries.end();) {
      if (it->heard || now - it->admitted_at < settings.limits.first_request_timeout) {
        ++it;
        continue;
      }
      auto guest = it->guest.lock();
      count(DoorClose::Deadline);
      deadline_log.warn("{}: closing {}: no {} within {} ({}) [timeout]", settings.log_name,
                        guest ? guest->peer() : it->address, settings.first_request,
                        duration_text(settings.limits.first_request_timeout),
                        settings.limit_names.first_request_timeout);
      it = entries.erase(it);
      if (settings.on_close) settings.on_close(DoorClose::Deadline);
      if (guest) late.push_back(std::move(guest));
    }
    publish_sizes();
    for (const auto& guest : late) guest->close_by_door();  // their leave() finds nothing left
    arm();
  }
};

Door::Door(asio::io_context& io, DoorSettings settings) : state_(std::make_shared<State>(io, std::move(settings))) {}

Door::~Door() {
  // A destructor must not throw: a timer that cannot be cancelled goes with the io_context.
  try {
    close();
  } catch (const std::exception& error) {
    spdlog::error("{}: closing the door failed: {}", state_->settings.log_name, error.what());
  }
}

std::optional<Door::Ticket> Door::admit(const std::string& address, std::weak_ptr<DoorGuest> guest) {
  State& s = *state_;
  const auto guest_now = guest.lock();
  const std::string peer = guest_now ? guest_now->peer() : address;
  if (s.served_count() >= s.settings.limits.max_served) {
    s.count(DoorClose::Full);
    s.log_full(peer);
    return std::nullopt;
  }
  const auto from_address = static_cast<std::size_t>(std::count_if(
      s.entries.begin(), s.entries.end(), [&](const State::Entry& e) { return !e.trusted && e.address == address; }));
  if (from_address >= s.settings.limits.max_waiting_per_address) {
    s.evict_for(peer, &address, s.settings.limit_names.max_waiting_per_address);
  }
  const std::size_t waiting = s.entries.size() - s.served_count();
  if (waiting >= s.settings.limits.max_waiting) s.evict_for(peer, nullptr, s.settings.limit_names.max_waiting);
  const Ticket ticket = s.next_ticket++;
  s.entries.push_back(State::Entry{ticket, address, std::move(guest), Clock::now(), false, false});
  {
    std::lock_guard lock(s.stats_mutex);
    ++s.stats.accepted;
  }
  s.publish_sizes();
  s.arm();
  return ticket;
}

void Door::heard(Ticket ticket) {
  const auto found = state_->find(ticket);
  if (found != state_->entries.end()) found->heard = true;
}

bool Door::trust(Ticket ticket) {
  State& s = *state_;
  const auto found = s.find(ticket);
  if (found == s.entries.end()) return false;
  found->heard = true;
  if (found->trusted) return true;
  if (s.served_count() >= s.settings.limits.max_served) {
    // Waiting connections that began while slots were free finished after the last was taken.
    const auto guest = found->guest.lock();
    s.count(DoorClose::Full);
    s.log_full(guest ? guest->peer() : found->address);
    return false;
  }
  found->trusted = true;
  s.publish_sizes();
  return true;
}

bool Door::trusted(Ticket ticket) const {
  const auto found = state_->find(ticket);
  return found != state_->entries.end() && found->trusted;
}

void Door::leave(Ticket ticket) { state_->forget(ticket); }

void Door::count_denied() { state_->count(DoorClose::Allow); }

void Door::close() {
  state_->closed = true;
  state_->timer.cancel();
}

const DoorSettings& Door::settings() const { return state_->settings; }

std::string Door::describe() const {
  const DoorSettings& s = state_->settings;
  return fmt::format(
      "at most {} connections served; at most {} waiting for a {}, {} per client address, each within {}",
      s.limits.max_served, s.limits.max_waiting, s.first_request, s.limits.max_waiting_per_address,
      s.limits.first_request_timeout.count() > 0 ? duration_text(s.limits.first_request_timeout) : "any time");
}

DoorStats Door::stats() const {
  std::lock_guard lock(state_->stats_mutex);
  return state_->stats;
}

}  // namespace sms::gateway
