#include "gateway/modbus_tcp/tcp_serving.h"

#include <future>
#include <optional>
#include <stdexcept>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>

namespace sms::gateway {

namespace asio = boost::asio;

class TcpServing::Impl {
 public:
  // The server's destructor closes what is still open, once the thread has ended.
  ~Impl() { stop(); }

  void post(std::function<void()> work) { asio::post(io_, std::move(work)); }
  asio::io_context& io() { return io_; }

  std::size_t listen(TcpServerOptions options, RequestHandler& handler) {
    if (thread_.joinable()) throw std::logic_error("TcpServing::listen called after run");
    servers_.push_back(std::make_unique<TcpServer>(io_, std::move(options), handler));
    servers_.back()->start();
    return servers_.size() - 1;
  }

  void run() {
    if (thread_.joinable()) throw std::logic_error("TcpServing::run called twice");
    thread_ = std::thread([this] { io_.run(); });
  }

  void drain(std::chrono::milliseconds grace) {
    if (servers_.empty() || !thread_.joinable()) return;
    auto closed = std::make_shared<std::promise<void>>();
    auto done = closed->get_future();
    asio::post(io_, [this, closed] {
      auto remaining = std::make_shared<std::size_t>(servers_.size());
      for (const auto& server : servers_) {
        server->shutdown([closed, remaining] {
          if (--*remaining == 0) closed->set_value();
        });
      }
    });
    if (done.wait_for(grace) != std::future_status::ready) {
      spdlog::warn("stopping: connections still waiting for the bus after {}; closing them", duration_text(grace));
      asio::post(io_, [this] {
        for (const auto& server : servers_) server->close_all();
      });
    }
  }

  void stop() {
    work_.reset();
    io_.stop();
    if (thread_.joinable()) thread_.join();
  }

  std::uint16_t port(std::size_t index) const { return index < servers_.size() ? servers_[index]->port() : 0; }
  std::vector<std::pair<std::string, DoorStats>> doors() const {
    std::vector<std::pair<std::string, DoorStats>> doors;
    for (const auto& server : servers_) doors.emplace_back(std::string(server->listener_name()), server->door_stats());
    return doors;
  }
  TcpServerStats stats() const {
    TcpServerStats total;
    for (const auto& server : servers_) {
      const TcpServerStats one = server->stats();
      total.open_connections += one.open_connections;
      total.accepted += one.accepted;
      total.refused += one.refused;
      total.denied += one.denied;
      total.requests += one.requests;
      total.bad_headers += one.bad_headers;
      total.idle_closed += one.idle_closed;
      for (std::size_t i = 0; i < total.refusals.size(); ++i) {
        total.refusals[i].max_connections += one.refusals[i].max_connections;
        total.refusals[i].allow += one.refusals[i].allow;
      }
    }
    return total;
  }

 private:
  asio::io_context io_;
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work_{io_.get_executor()};
  std::vector<std::unique_ptr<TcpServer>> servers_;
  std::thread thread_;
};

TcpServing::TcpServing() : impl_(std::make_unique<Impl>()) {}
TcpServing::~TcpServing() = default;
void TcpServing::post(std::function<void()> work) { impl_->post(std::move(work)); }
boost::asio::io_context& TcpServing::io() { return impl_->io(); }
std::size_t TcpServing::listen(TcpServerOptions options, RequestHandler& handler) {
  return impl_->listen(std::move(options), handler);
}
void TcpServing::run() { impl_->run(); }
void TcpServing::drain(std::chrono::milliseconds grace) { impl_->drain(grace); }
void TcpServing::stop() { impl_->stop(); }
std::uint16_t TcpServing::port(std::size_t index) const { return impl_->port(index); }
TcpServerStats TcpServing::stats() const { return impl_->stats(); }
std::vector<std::pair<std::string, DoorStats>> TcpServing::doors() const { return impl_->doors(); }

}  // namespace sms::gateway
