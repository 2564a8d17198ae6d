#include "gateway/console/console_websocket.h"

#include <deque>

#include <spdlog/spdlog.h>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>
#include <boost/beast/websocket/ssl.hpp>

namespace sms::gateway::console {
namespace {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

// A slow page that lets this many pushes pile up is closed (it reconnects by itself).
constexpr std::size_t kMaxQueuedMessages = 64;

template <typename Transport>
class WebSocketSession final : public Socket, public std::enable_shared_from_this<WebSocketSession<Transport>> {
 public:
  WebSocketSession(Transport transport, ConnectionHost& host, OpenedSocket opened, Door::Ticket ticket)
      : ws_(std::move(transport)),
        host_(host),
        stream_(std::move(opened.first)),
        who_(std::move(opened.second)),
        ticket_(ticket) {
    host_.add(this);
  }
  ~WebSocketSession() override {
    host_.remove(this);
    host_.remove_socket(this);
  }

  void accept(HttpRequest request) {
    ws_.read_message_max(host_.limits().max_message_bytes);
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    ws_.set_option(websocket::stream_base::decorator([](websocket::response_type& response) {
      const std::string_view name = console_server_name();
      response.set(http::field::server, beast::string_view(name.data(), name.size()));
    }));
    beast::get_lowest_layer(ws_).expires_never();
    ws_.async_accept(request, [self = this->shared_from_this()](const beast::error_code& error) {
      if (error) return self->finish();
      self->host_.add_socket(self.get());
      self->read();
    });
  }

  void tick(SteadyClock::time_point now, bool push) override {
    if (finished_) return;
    stream_->sample(now);
    if (!push) return;
    if (auto message = stream_->flush(now)) send(std::move(*message));
  }

  void close() override {
    finish();
    beast::error_code ignored;
    auto& socket = beast::get_lowest_layer(ws_).socket();
    socket.shutdown(tcp::socket::shutdown_both, ignored);
    socket.close(ignored);
  }

 private:
  void read() {
    ws_.async_read(buffer_, [self = this->shared_from_this()](const beast::error_code& error, std::size_t) {
      if (error) {
        if (error != websocket::error::closed && error != asio::error::operation_aborted) {
          spdlog::debug("console: WebSocket of {} ended: {}", self->who_, error.message());
        }
        return self->finish();
      }
      const std::string text = beast::buffers_to_string(self->buffer_.data());
      self->buffer_.consume(self->buffer_.size());
      if (!self->finished_) {
        std::weak_ptr<WebSocketSession> weak = self;
        self->stream_->on_message(text, [weak](std::string message) {
          if (auto session = weak.lock()) session->send(std::move(message));
        });
      }
      self->read();
    });
  }

  void send(std::string message) {
    if (finished_) return;
    if (queue_.size() >= kMaxQueuedMessages) {
      spdlog::info("console: closing the WebSocket of {}: it reads slower than the gateway pushes", who_);
      return close();
    }
    queue_.push_back(std::move(message));
    if (queue_.size() == 1) write();
  }

  void write() {
    ws_.text(true);
    ws_.async_write(asio::buffer(queue_.front()),
                    [self = this->shared_from_this()](const beast::error_code& error, std::size_t) {
                      if (error) return self->finish();
                      self->queue_.pop_front();
                      if (!self->queue_.empty()) self->write();
                    });
  }

  // The page is gone (or the server stops): the stream hears it once (a hold-to-run move stops).
  void finish() {
    if (finished_) return;
    finished_ = true;
    host_.door().leave(ticket_);
    host_.remove_socket(this);
    stream_->on_close();
  }

  websocket::stream<Transport> ws_;
  ConnectionHost& host_;
  std::unique_ptr<Stream> stream_;
  std::string who_;
  beast::flat_buffer buffer_;
  std::deque<std::string> queue_;
  Door::Ticket ticket_;
  bool finished_ = false;
};

}  // namespace

template <typename Transport>
void start_websocket(Transport transport, ConnectionHost& host, OpenedSocket opened, Door::Ticket ticket,
                     HttpRequest request) {
  std::make_shared<WebSocketSession<Transport>>(std::move(transport), host, std::move(opened), ticket)
      ->accept(std::move(request));
}

template void start_websocket<beast::tcp_stream>(beast::tcp_stream, ConnectionHost&, OpenedSocket, Door::Ticket,
                                                 HttpRequest);
template void start_websocket<beast::ssl_stream<beast::tcp_stream>>(beast::ssl_stream<beast::tcp_stream>,
                                                                    ConnectionHost&, OpenedSocket, Door::Ticket,
                                                                    HttpRequest);

}  // namespace sms::gateway::console
