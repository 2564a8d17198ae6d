// Who a request is and whether it is admitted (gateway/console/console_admission.h), without
// sockets: here, a WebSocket upgrade's origin.
#include "gateway/console/console_admission.h"

#include <gtest/gtest.h>

#include <string>

namespace sms::gateway::console {
namespace {

// A WebSocket is opened only by this console's own pages: its scheme and the host it was asked
// by. An https:// page may not open the plain HTTP console's socket, nor the reverse, nor may
// another site's page.
TEST(ConsoleAdmission, AWebSocketOpensFromTheConsolesOwnOriginOnly) {
  const config::Config config;
  for (const bool https : {false, true}) {
    config::ConsoleConfig console;
    if (https) {
      console.certificate = "console.pem";
      console.key = "console.key";
    }
    SessionStore sessions(std::chrono::seconds(600));
    const Admission admission(config, console, sessions);
    Identity identity;
    identity.session = sessions.create(Principal{"alice", config::Role::Operate, "password"});
    const std::string target = "/ws/overview?csrf=" + identity.session->csrf;
    const std::string own = std::string(https ? "https" : "http") + "://gw.local:8080";
    const std::string other_scheme = std::string(https ? "http" : "https") + "://gw.local:8080";
    for (const auto& [origin, admitted] :
         {std::pair{own, true}, std::pair{other_scheme, false}, std::pair{std::string("http://evil.example"), false},
          std::pair{own + ".evil.example", false}}) {
      RequestFacts facts;
      facts.target = target;
      facts.origin = origin;
      facts.host = "gw.local:8080";
      EXPECT_EQ(!admission.socket_refusal(identity, facts).has_value(), admitted)
          << (https ? "HTTPS" : "HTTP") << " console, origin " << origin;
    }
  }
}

}  // namespace
}  // namespace sms::gateway::console
