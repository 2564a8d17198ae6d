#include "gateway/net/listener.h"

#include <future>
#include <memory>
#include <stdexcept>

#include <boost/asio/ip/address.hpp>
#include <boost/asio/post.hpp>

namespace sms::gateway {

namespace asio = boost::asio;
using asio::ip::tcp;

namespace {

std::string advice_for(const boost::system::error_code& error, const std::string& host, const ListenerRole& role) {
  if (error == asio::error::address_in_use) {
    return "; another program (another sms-gateway?) is listening there: stop it, or choose a free port with " +
           std::string(role.setting);
  }
  if (error == asio::error::access_denied) {
    return "; ports below 1024 need root or CAP_NET_BIND_SERVICE: run with that capability, or use a port above 1023 "
           "(e.g. " +
           host + ":" + std::to_string(role.unprivileged_port) + ")";
  }
  if (error == boost::system::errc::address_not_available) {
    return "; no network interface of this machine has that address: use 0.0.0.0 (every interface), 127.0.0.1, or an "
           "address this machine owns";
  }
  return {};
}

}  // namespace

void open_listener(tcp::acceptor& acceptor, const std::string& host, std::uint16_t port, const ListenerRole& role) {
  const std::string where = host + ":" + std::to_string(port);
  const std::string failed = "cannot " + std::string(role.action) + " on " + where + ": ";
  boost::system::error_code error;
  tcp::endpoint endpoint;
  if (const auto address = asio::ip::make_address(host, error); !error) {
    endpoint = {address, port};
  } else {
    tcp::resolver resolver(acceptor.get_executor());
    const auto results = resolver.resolve(host, std::to_string(port), error);
    if (error || results.empty()) {
      throw std::runtime_error(failed + "the host does not resolve (" + error.message() +
                               "); give an IP address such as 0.0.0.0 or 127.0.0.1");
    }
    endpoint = results.begin()->endpoint();
  }
  acceptor.open(endpoint.protocol(), error);
  if (!error) acceptor.set_option(tcp::acceptor::reuse_address(true), error);
  if (!error) acceptor.bind(endpoint, error);
  if (!error) acceptor.listen(asio::socket_base::max_listen_connections, error);
  if (error) {
    const std::string message = failed + error.message() + advice_for(error, host, role);
    boost::system::error_code ignored;
    acceptor.close(ignored);
    throw std::runtime_error(message);
  }
}

void close_and_join(boost::asio::io_context& io, std::thread& thread, const std::function<void()>& close_all) {
  if (!thread.joinable()) return;
  auto closed = std::make_shared<std::promise<void>>();
  auto done = closed->get_future();
  boost::asio::post(io, [&close_all, closed] {
    close_all();
    closed->set_value();
  });
  done.wait();
  io.stop();
  thread.join();
}

}  // namespace sms::gateway
