#include "gateway/console/console_commission.h"

#include <filesystem>

#include <spdlog/spdlog.h>

#include "gateway/service/unit_catalog.h"
#include "gateway/tools/tag_list.h"
#include "gateway/tools/tool_scan.h"
#include "gateway/tools/tool_servo.h"
#include "modbus_map/baud_tables.h"
#include "modbus_map/tables.h"

namespace sms::gateway::console {

namespace {

using nlohmann::json;

std::string canonical(const std::string& path) {
  std::error_code error;
  const auto resolved = std::filesystem::weakly_canonical(path, error);
  return error ? path : resolved.string();
}

// The line and servo a commissioning request names, checked.
struct LineRequest {
  LinkSettings link;
  modbus_map::TableId table = modbus_map::TableId::Sts;
  std::uint8_t id = 1;
  json body;
};

Expected<LineRequest> line_request(const ApiCall& call, bool needs_baud) {
  json body = json::parse(call.body, nullptr, false);
  if (body.is_discarded() || !body.is_object()) return unexpected(std::string("the body must be a JSON object"));
  LineRequest request;
  request.body = body;
  const auto device = body.find("device");
  if (device == body.end() || !device->is_string() || device->get<std::string>().empty() ||
      device->get<std::string>().size() > 256) {
    return unexpected(std::string("`device` (the serial device, e.g. /dev/ttyUSB1) is missing"));
  }
  request.link.device = device->get<std::string>();
  if (const auto owner = call.services.commissioning().owner_of(request.link.device)) return unexpected(*owner);
  const auto protocol_name = body.value("protocol", std::string("feetech"));
  const auto protocol = protocol::bus_protocol_from_string(protocol_name);
  if (!protocol) return unexpected("`protocol` must be feetech, d55d or modbus-rtu, got " + printable(protocol_name));
  request.link.protocol = *protocol;
  request.table = tool_protocol(*protocol).default_table;
  if (const auto table = body.find("table");
      table != body.end() && table->is_string() && !table->get<std::string>().empty()) {
    const auto id = modbus_map::table_from_name(table->get<std::string>());
    if (!id || modbus_map::table(*id).protocol != *protocol) {
      return unexpected("table " + printable(table->get<std::string>()) + " is not spoken on " + protocol_name +
                        " buses");
    }
    request.table = *id;
  }
  const auto baud = body.find("baud");
  if (baud != body.end() && baud->is_number_unsigned()) {
    request.link.baud = baud->get<std::uint32_t>();
    if (auto code = modbus_map::baud_code(*protocol, request.link.baud); !code) return unexpected(code.error());
  } else if (needs_baud) {
    return unexpected("`baud` (the servo's current rate) is missing; " + modbus_map::valid_bauds_text(*protocol));
  } else {
    request.link.baud = modbus_map::baud_table(*protocol).front().bps;
  }
  const auto id = body.find("id");
  if (id != body.end()) {
    if (!id->is_number_unsigned() || id->get<unsigned>() > 253) return unexpected(std::string("`id` must be 0-253"));
    request.id = static_cast<std::uint8_t>(id->get<unsigned>());
  }
  return request;
}

void start_job(const std::shared_ptr<ApiCall>& call, std::string kind,
               std::function<json(const std::function<void(const std::string&)>&)> work) {
  if (!call->services.commissioning().start(std::move(kind), std::move(work))) {
    return call->answer(HttpAnswer::error(409, "a commissioning job runs already; wait for it to finish"));
  }
  call->answer(HttpAnswer::json(202, call->services.commissioning().state()));
}

// A job on one servo over a freshly opened line.
using ServoJob = Expected<std::string> (*)(ServoLink&, const ToolTarget&, std::uint32_t, const Say&);

}  // namespace

Commissioning::Commissioning(const config::Config& config, BusLending lending)
    : config_(config), lending_(std::move(lending)) {}

Commissioning::~Commissioning() {
  if (worker_.joinable()) worker_.join();
}

std::optional<std::string> Commissioning::owner_of(const std::string& device) const {
  const std::string wanted = canonical(device);
  for (std::size_t i = 0; i < config_.buses.size(); ++i) {
    const auto& bus = config_.buses[i];
    if (canonical(bus.device) != wanted) continue;
    if (lending_.lent && lending_.lent(i)) return std::nullopt;
    return device + " is the line of bus `" + bus.name +
           "`, which the gateway runs: stop the bus on this page first (its servos get their safe stop), or "
           "commission a line no bus owns";
  }
  for (const auto& port : config_.modbus_rtu_slave) {
    if (canonical(port.device) == wanted) return device + " is an upstream Modbus RTU port of this gateway";
  }
  return std::nullopt;
}

std::optional<std::size_t> Commissioning::bus_index(const std::string& name) const {
  for (std::size_t i = 0; i < config_.buses.size(); ++i) {
    if (config_.buses[i].name == name) return i;
  }
  return std::nullopt;
}

bool Commissioning::start(std::string kind, std::function<json(const std::function<void(const std::string&)>&)> work) {
  std::lock_guard lock(mutex_);
  if (running_) return false;
  if (worker_.joinable()) worker_.join();  // the last job has finished: its thread ends at once
  running_ = true;
  kind_ = std::move(kind);
  log_.clear();
  result_ = nullptr;
  error_.clear();
  worker_ = std::thread([this, work = std::move(work)] {
    json result;
    std::string error;
    try {
      result = work([this](const std::string& line) {
        std::lock_guard lock(mutex_);
        if (log_.size() < 2000) log_.push_back(line);
      });
    } catch (const std::exception& failure) {
      error = failure.what();
    }
    std::lock_guard lock(mutex_);
    if (result.contains("error")) {
      error = result["error"].get<std::string>();
    } else if (result.contains("config_yaml")) {
      config_yaml_ = result["config_yaml"].get<std::string>();
    }
    result_ = std::move(result);
    error_ = std::move(error);
    running_ = false;
    spdlog::info("console: commissioning {} finished{}", kind_, error_.empty() ? "" : ": " + error_);
  });
  return true;
}

json Commissioning::state() const {
  json buses = json::array();
  for (std::size_t i = 0; i < config_.buses.size(); ++i) {
    const auto& bus = config_.buses[i];
    buses.push_back({{"name", bus.name},
                     {"device", bus.device},
                     {"protocol", std::string(protocol::to_string(bus.protocol))},
                     {"baud", bus.baud},
                     {"stoppable", static_cast<bool>(lending_.lend)},
                     {"lent", lending_.lent && lending_.lent(i)}});
  }
  std::lock_guard lock(mutex_);
  return {{"running", running_}, {"kind", kind_},   {"log", log_},
          {"result", result_},   {"error", error_}, {"config_ready", !config_yaml_.empty()},
          {"buses", buses}};
}

std::string Commissioning::config_yaml() const {
  std::lock_guard lock(mutex_);
  return config_yaml_;
}

void api_commission_state(const std::shared_ptr<ApiCall>& call) {
  call->answer(HttpAnswer::json(200, call->services.commissioning().state()));
}

void api_commission_config(const std::shared_ptr<ApiCall>& call) {
  const std::string yaml = call->services.commissioning().config_yaml();
  if (yaml.empty()) return call->answer(HttpAnswer::error(404, "no scan yet: scan a line first"));
  call->answer(HttpAnswer{200,
                          "application/yaml; charset=utf-8",
                          yaml,
                          {{"Content-Disposition", "attachment; filename=\"sms-gateway-scan.yaml\""}}});
}

void api_tags(const std::shared_ptr<ApiCall>& call) {
  // The same lists as `sms-gateway tags` (gateway/tools/tag_list.h), of the running configuration,
  // aimed at this gateway's Modbus TCP listener.
  const config::Config& config = call->services.config();
  const std::string file(call->params.get("file").value_or(""));
  const std::string& listen = config.modbus_tcp.listen.host;
  const FlowTarget target{listen.empty() || listen == "0.0.0.0" || listen == "::" ? "127.0.0.1" : listen,
                          config.modbus_tcp.listen.port};
  const auto attachment = [](const std::string& name) {
    return std::vector<std::pair<std::string, std::string>>{
        {"Content-Disposition", "attachment; filename=\"" + name + "\""}};
  };
  try {
    const UnitCatalog catalog(config);
    if (file == "tags.csv") {
      return call->answer(HttpAnswer{200, "text/csv; charset=utf-8", tags_csv(tag_list(config, catalog)),
                                     attachment("sms-gateway-tags.csv")});
    }
    if (file == "node-red.json") {
      return call->answer(HttpAnswer{200, "application/json", node_red_flow(config, catalog, target).dump(2),
                                     attachment("sms-gateway-node-red.json")});
    }
    if (file == "fuxa.json") {
      return call->answer(HttpAnswer{200, "application/json", fuxa_devices(tag_list(config, catalog), target).dump(2),
                                     attachment("sms-gateway-fuxa.json")});
    }
  } catch (const std::exception& error) {
    return call->answer(HttpAnswer::error(500, std::string("tag list: ") + error.what()));
  }
  call->answer(HttpAnswer::error(404, "no tag list " + file + ": tags.csv, node-red.json or fuxa.json"));
}

void api_commission_scan(const std::shared_ptr<ApiCall>& call) {
  auto request = line_request(*call, false);
  if (!request) return call->answer(HttpAnswer::error(400, "scan: " + request.error()));
  ScanOptions options;
  options.table = request->table;
  if (const auto bauds = request->body.find("bauds"); bauds != request->body.end() && bauds->is_array()) {
    for (const auto& baud : *bauds) {
      if (!baud.is_number_unsigned() || !modbus_map::baud_code(request->link.protocol, baud.get<std::uint32_t>())) {
        return call->answer(HttpAnswer::error(
            400, "scan: `bauds` must be rates of the table: " + modbus_map::valid_bauds_text(request->link.protocol)));
      }
      options.bauds.push_back(baud.get<std::uint32_t>());
    }
  }
  if (const auto last = request->body.find("last_id"); last != request->body.end()) {
    if (!last->is_number_unsigned() || last->get<unsigned>() > 253) {
      return call->answer(HttpAnswer::error(400, "scan: `last_id` must be 0-253"));
    }
    for (unsigned id = tool_protocol(request->link.protocol).first_id; id <= last->get<unsigned>(); ++id) {
      options.ids.push_back(static_cast<std::uint8_t>(id));
    }
  }
  LinkSettings link = request->link;
  start_job(call, "scan of " + link.device, [link, options](const auto& say) -> json {
    auto line = make_servo_link(link);
    if (auto opened = line->open(); !opened) return {{"error", opened.error()}};
    auto report = scan_bus(*line, options, say);
    if (!report) return {{"error", report.error()}};
    json found = json::array();
    for (const auto& servo : report->found) {
      found.push_back({{"baud", servo.baud},
                       {"id", servo.id},
                       {"table", std::string(modbus_map::table(servo.table).name)},
                       {"conflict", servo.conflict},
                       {"note", servo.note}});
    }
    return {{"found", found}, {"summary", format_scan(*report)}, {"config_yaml", scan_config_yaml(*report, link)}};
  });
}

namespace {

void servo_job(const std::shared_ptr<ApiCall>& call, const std::string& what, const char* value_key, ServoJob job) {
  auto request = line_request(*call, true);
  if (!request) return call->answer(HttpAnswer::error(400, what + ": " + request.error()));
  std::uint32_t value = 0;
  if (value_key != nullptr) {
    const auto it = request->body.find(value_key);
    if (it == request->body.end() || !it->is_number_unsigned()) {
      return call->answer(HttpAnswer::error(400, what + ": `" + value_key + "` is missing"));
    }
    value = it->get<std::uint32_t>();
  }
  const LinkSettings link = request->link;
  const ToolTarget target{request->table, request->id, false};
  start_job(call, what + " on " + link.device, [link, target, value, job](const auto& say) -> json {
    auto line = make_servo_link(link);
    if (auto opened = line->open(); !opened) return {{"error", opened.error()}};
    auto done = job(*line, target, value, say);
    if (!done) return {{"error", done.error()}};
    return {{"summary", *done}};
  });
}

}  // namespace

void api_commission_set_id(const std::shared_ptr<ApiCall>& call) {
  servo_job(call, "set-id", "new_id",
            [](ServoLink& link, const ToolTarget& target, std::uint32_t value, const Say& say) {
              if (value > 253) return Expected<std::string>(unexpected(std::string("`new_id` must be 0-253")));
              return set_servo_id(link, target, static_cast<std::uint8_t>(value), say);
            });
}

void api_commission_set_baud(const std::shared_ptr<ApiCall>& call) {
  servo_job(call, "set-baud", "new_baud",
            [](ServoLink& link, const ToolTarget& target, std::uint32_t value, const Say& say) {
              return set_servo_baud(link, target, value, say);
            });
}

void api_commission_calibrate(const std::shared_ptr<ApiCall>& call) {
  servo_job(call, "calibrate-middle", nullptr,
            [](ServoLink& link, const ToolTarget& target, std::uint32_t, const Say& say) {
              return calibrate_middle(link, target, say);
            });
}

void api_commission_factory_reset(const std::shared_ptr<ApiCall>& call) {
  servo_job(call, "factory-reset", nullptr,
            [](ServoLink& link, const ToolTarget& target, std::uint32_t, const Say& say) {
              return factory_reset(link, target, say);
            });
}

namespace {

// The bus a stop-bus / start-bus request names, checked; `needs_confirm`: stopping asks for
// "confirm": true (the page asks the operator first).
Expected<std::size_t> named_bus(const ApiCall& call, const std::string& what, bool needs_confirm) {
  const json body = json::parse(call.body, nullptr, false);
  const auto name = body.is_object() ? body.find("bus") : body.end();
  if (!body.is_object() || name == body.end() || !name->is_string()) {
    return unexpected(what + ": `bus` (the name of a configured bus) is missing");
  }
  const auto index = call.services.commissioning().bus_index(name->get<std::string>());
  if (!index) return unexpected(what + ": no bus " + printable(name->get<std::string>()) + " in the configuration");
  if (!call.services.commissioning().lending().lend) {
    return unexpected(what + ": this gateway cannot stop its buses from the console");
  }
  if (needs_confirm && !body.value("confirm", false)) {
    return unexpected(
        "stop-bus: stopping bus " + call.services.config().buses[*index].name +
        " stops its servos (their safe stop) and refuses PLC writes to them until it is started again; send "
        "\"confirm\": true to do it");
  }
  return *index;
}

}  // namespace

namespace {

// stop-bus and start-bus: a job like any other, so never while a scan or a set-id still holds the
// bus's line open. The worker thread calls the gateway (BusLending), not Services (console thread only).
void bus_job(const std::shared_ptr<ApiCall>& call, const std::string& what, bool stop) {
  const auto index = named_bus(*call, what, stop);
  if (!index) return call->answer(HttpAnswer::error(400, index.error()));
  const std::string bus = call->services.config().buses[*index].name;
  const std::string who = "the browser console (" + call->who.name + ")";
  const BusLending& lending = call->services.commissioning().lending();
  auto act = stop ? lending.lend : lending.take_back;
  start_job(call, (stop ? "stop bus " : "start bus ") + bus,
            [act, index = *index, who, bus, stop](const auto& say) -> json {
              if (stop) say("stopping bus " + bus + ": its servos get their safe stop, then its line is closed");
              auto done = act(index, who);
              if (!done) return {{"error", done.error()}};
              return {{"summary", *done}};
            });
}

}  // namespace

void api_commission_stop_bus(const std::shared_ptr<ApiCall>& call) { bus_job(call, "stop-bus", true); }

void api_commission_start_bus(const std::shared_ptr<ApiCall>& call) { bus_job(call, "start-bus", false); }

}  // namespace sms::gateway::console
