#pragma once
// The console's own HTTPS (console.certificate and console.key, docs/CONSOLE.md "HTTPS"): for
// password logins across the network, independent of Modbus/TCP Security's files (console.tls
// uses those, with client certificates). No client certificates here: users log in.
#include <memory>
#include <string>

#include <boost/asio/ssl/context.hpp>

namespace sms::gateway::console {

// A TLS 1.2+ server context with `certificate` (PEM, may hold the chain) and its unencrypted PEM
// `key`. Throws std::runtime_error naming the file, what is wrong and what to do.
std::shared_ptr<boost::asio::ssl::context> console_tls_context(const std::string& certificate, const std::string& key);

}  // namespace sms::gateway::console
