#pragma once
// A Modbus/TCP Security client for the end-to-end tests: Boost.Asio SSL with a certificate made by
// tests/e2e/make_test_certs.sh and hand-written MBAP framing (tls_test.cpp, front_door_test.cpp).
#include <sys/socket.h>
#include <sys/time.h>

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/read.hpp>
#include <boost/asio/ssl.hpp>
#include <boost/asio/write.hpp>

namespace sms::e2e {

using Pdu = std::vector<std::uint8_t>;

// A read that waits longer than this on a socket fails instead of hanging the test.
inline void set_receive_timeout(int fd) {
  timeval timeout{5, 0};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
}

// A Modbus/TCP Security client: TLS with the certificate `name` of the test's directory.
class TlsClient {
 public:
  TlsClient(const std::string& certs, const std::string& name, std::uint16_t port, const std::string& ca = "ca")
      : context_(boost::asio::ssl::context::tls_client) {
    namespace asio = boost::asio;
    namespace ssl = asio::ssl;
    context_.load_verify_file(certs + "/" + ca + ".crt");
    context_.use_certificate_chain_file(certs + "/" + name + ".crt");
    context_.use_private_key_file(certs + "/" + name + ".key", ssl::context::pem);
    context_.set_verify_mode(ssl::verify_peer);
    // Made after the context has its certificate: a stream copies what the context has then.
    stream_.emplace(io_, context_);
    stream_->set_verify_callback(ssl::host_name_verification("localhost"));
    stream_->lowest_layer().connect(asio::ip::tcp::endpoint(asio::ip::make_address("127.0.0.1"), port), error_);
    if (error_) return;
    set_receive_timeout(stream_->lowest_layer().native_handle());
    stream_->handshake(ssl::stream_base::client, error_);
  }

  // TLS 1.3: the client's handshake is done before the server has checked its certificate, so
  // a refusal shows on the first read. Also a connection that could not be made.
  const boost::system::error_code& handshake_error() const { return error_; }

  // One request; the answer's PDU, or nullopt when the connection gave none.
  std::optional<Pdu> request(const Pdu& pdu, int unit = 1) {
    namespace asio = boost::asio;
    if (error_) return std::nullopt;
    ++transaction_;
    Pdu adu{static_cast<std::uint8_t>(transaction_ >> 8),
            static_cast<std::uint8_t>(transaction_),
            0,
            0,
            static_cast<std::uint8_t>((pdu.size() + 1) >> 8),
            static_cast<std::uint8_t>(pdu.size() + 1),
            static_cast<std::uint8_t>(unit)};
    adu.insert(adu.end(), pdu.begin(), pdu.end());
    boost::system::error_code error;
    asio::write(*stream_, asio::buffer(adu), error);
    if (error) return std::nullopt;
    std::array<std::uint8_t, 7> header{};
    asio::read(*stream_, asio::buffer(header), error);
    if (error) return std::nullopt;
    const std::size_t length = (std::size_t{header[4]} << 8 | header[5]);
    if (length < 2 || header[0] != adu[0] || header[1] != adu[1]) return std::nullopt;
    Pdu answer(length - 1);
    asio::read(*stream_, asio::buffer(answer), error);
    if (error) return std::nullopt;
    return answer;
  }

  // The TLS stream, for tests that look at how the connection ends.
  boost::asio::ssl::stream<boost::asio::ip::tcp::socket>& stream() { return *stream_; }

 private:
  boost::asio::io_context io_;
  boost::asio::ssl::context context_;
  std::optional<boost::asio::ssl::stream<boost::asio::ip::tcp::socket>> stream_;
  boost::system::error_code error_;
  std::uint16_t transaction_ = 0;
};

// The configuration lines the TLS tests share: modbus_tcp.tls with the test CA's server
// certificate on a port of the gateway's choosing and the roles the certificates map to (`extra`:
// more lines of it, indented by 4), and one bus `line` on `pty` with one sts servo.
inline std::string tls_listener_yaml(const std::string& certs, const std::string& extra = "") {
  return "  tls:\n"
         "    listen: \"127.0.0.1:0\"\n"
         "    certificate: \"" +
         certs + "/server.crt\"\n    private_key: \"" + certs + "/server.key\"\n    ca: \"" + certs +
         "/ca.crt\"\n"
         "    roles: {hmi-2.plant: read, plc-3: operate}\n" +
         extra;
}
inline std::string one_servo_yaml(const std::string& pty) {
  return "buses:\n  - {name: line, device: \"" + pty +
         "\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}\nservos:\n  - {bus: line, id: 1, table: "
         "sts}\n";
}

}  // namespace sms::e2e
