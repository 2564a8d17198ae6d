#pragma once
// The console's commissioning page (`engineer`): scan a serial line no running bus owns across
// its protocol's baud table (or a bus's own line after stopping the bus from the page: its
// servos get their safe stop first), give a servo another ID or baud, calibrate its mid-point,
// reset it to factory values where the protocol has an instruction for it, and download the
// scan as a configuration — the integrator tools' own code (gateway/tools: scan_bus,
// set_servo_id, set_servo_baud, calibrate_middle, factory_reset, scan_config_yaml), run one job
// at a time on a worker thread so the console keeps answering; the page polls the job's progress.
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "config/config.h"
#include "gateway/console/console_routes.h"
#include "protocol/expected.h"

namespace sms::gateway::console {

// Lending a running bus's serial line to commissioning (docs/CONSOLE.md); `bus` indexes
// config.buses. lend and take_back block (the commissioning worker thread calls them) and give
// the page's summary or what went wrong; lent: any thread.
struct BusLending {
  std::function<Expected<std::string>(std::size_t bus, const std::string& who)> lend;
  std::function<Expected<std::string>(std::size_t bus, const std::string& who)> take_back;
  std::function<bool(std::size_t bus)> lent;
};

class Commissioning {
 public:
  Commissioning(const config::Config& config, BusLending lending);
  ~Commissioning();  // waits for a running job (each transaction is bounded by its timeout)

  // Why `device` may not be used: a running bus or an upstream RTU port owns it; nullopt: free
  // (no one's, or the line of a bus stopped for commissioning).
  std::optional<std::string> owner_of(const std::string& device) const;
  // The index in config.buses of the bus named `name`.
  std::optional<std::size_t> bus_index(const std::string& name) const;
  const BusLending& lending() const { return lending_; }
  // Starts `work` as the job `kind`; false when a job runs already.
  bool start(std::string kind, std::function<nlohmann::json(const std::function<void(const std::string&)>& say)> work);
  nlohmann::json state() const;
  std::string config_yaml() const;

 private:
  const config::Config& config_;
  const BusLending lending_;
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
// GET /api/tags/{file}: the running configuration's tag lists (tags.csv, node-red.json,
// fuxa.json), as `sms-gateway tags` writes them (docs/HMI.md).
void api_tags(const std::shared_ptr<ApiCall>& call);
void api_commission_scan(const std::shared_ptr<ApiCall>& call);
void api_commission_set_id(const std::shared_ptr<ApiCall>& call);
void api_commission_set_baud(const std::shared_ptr<ApiCall>& call);
void api_commission_calibrate(const std::shared_ptr<ApiCall>& call);
void api_commission_factory_reset(const std::shared_ptr<ApiCall>& call);
void api_commission_stop_bus(const std::shared_ptr<ApiCall>& call);
void api_commission_start_bus(const std::shared_ptr<ApiCall>& call);

}  // namespace sms::gateway::console
