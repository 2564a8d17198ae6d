#pragma once
// The console's commissioning page (`engineer`): scan a serial line no running bus owns across
// its protocol's baud table, give a servo another ID or baud, calibrate its mid-point, and
// download the scan as a configuration — the integrator tools' own code (gateway/tools:
// scan_bus, set_servo_id, set_servo_baud, calibrate_middle, scan_config_yaml), run one job at a
// time on a worker thread so the console keeps answering; the page polls the job's progress.
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "config/config.h"
#include "gateway/console/console_routes.h"

namespace sms::gateway::console {

class Commissioning {
 public:
  explicit Commissioning(const config::Config& config);
  ~Commissioning();  // waits for a running job (each transaction is bounded by its timeout)

  // Why `device` may not be used: a configured bus or upstream RTU port owns it; nullopt: free.
  std::optional<std::string> owner_of(const std::string& device) const;
  // Starts `work` as the job `kind`; false when a job runs already.
  bool start(std::string kind, std::function<nlohmann::json(const std::function<void(const std::string&)>& say)> work);
  nlohmann::json state() const;
  std::string config_yaml() const;

 private:
  const config::Config& config_;
  mutable std::mutex mutex_;
  bool running_ = false;
  std::string kind_;
  std::vector<std::string> log_;
  nlohmann::json result_;
  std::string error_;
  std::string config_yaml_;
  std::thread worker_;
};

void api_commission_state(const std::shared_ptr<ApiCall>& call);
void api_commission_config(const std::shared_ptr<ApiCall>& call);
void api_commission_scan(const std::shared_ptr<ApiCall>& call);
void api_commission_set_id(const std::shared_ptr<ApiCall>& call);
void api_commission_set_baud(const std::shared_ptr<ApiCall>& call);
void api_commission_calibrate(const std::shared_ptr<ApiCall>& call);

}  // namespace sms::gateway::console
