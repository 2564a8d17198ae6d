#include "gateway/tcp_serving.h"

#include <future>
#include <optional>
#include <stdexcept>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <spdlog/spdlog.h>

namespace sms::gateway {

namespace asio = boost::asio;

class TcpServing::Impl {
 public:
  // The server's destructor closes what is still open, once the thread has ended.
  ~Impl() { stop(); }

  void post(std::function<void()> work) { asio::post(io_, std::move(work)); }

  void listen(TcpServerOptions options, RequestHandler& handler) {
    if (server_) throw std::logic_error("TcpServing::listen called twice");
    server_ = std::make_unique<TcpServer>(io_, std::move(options), handler);
    server_->start();
  }

  void run() {
    if (thread_.joinable()) throw std::logic_error("TcpServing::run called twice");
    thread_ = std::thread([this] { io_.run(); });
  }

  void drain(std::chrono::milliseconds grace) {
    if (!server_ || !thread_.joinable()) return;
    auto closed = std::make_shared<std::promise<void>>();
    auto done = closed->get_future();
    asio::post(io_, [this, closed] { server_->shutdown([closed] { closed->set_value(); }); });
    if (done.wait_for(grace) != std::future_status::ready) {
      spdlog::warn("stopping: connections still waiting for the bus after {}; closing them", duration_text(grace));
      asio::post(io_, [this] { server_->close_all(); });
    }
  }

  void stop() {
    work_.reset();
    io_.stop();
    if (thread_.joinable()) thread_.join();
  }

  std::uint16_t port() const { return server_ ? server_->port() : 0; }
  TcpServerStats stats() const { return server_ ? server_->stats() : TcpServerStats{}; }

 private:
  asio::io_context io_;
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work_{io_.get_executor()};
  std::unique_ptr<TcpServer> server_;
  std::thread thread_;
};

TcpServing::TcpServing() : impl_(std::make_unique<Impl>()) {}
TcpServing::~TcpServing() = default;
void TcpServing::post(std::function<void()> work) { impl_->post(std::move(work)); }
void TcpServing::listen(TcpServerOptions options, RequestHandler& handler) {
  impl_->listen(std::move(options), handler);
}
void TcpServing::run() { impl_->run(); }
void TcpServing::drain(std::chrono::milliseconds grace) { impl_->drain(grace); }
void TcpServing::stop() { impl_->stop(); }
std::uint16_t TcpServing::port() const { return impl_->port(); }
TcpServerStats TcpServing::stats() const { return impl_->stats(); }

}  // namespace sms::gateway
