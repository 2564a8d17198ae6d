#pragma once
// The Sparkplug node's insides (sparkplug_node.h is its face), shared by the files that each hold
// one concern: the node as a Modbus client of the router (sparkplug_node.cpp), the MQTT session and
// its bdSeq (sparkplug_session.cpp), births and deaths (sparkplug_births.cpp), the data between
// them (sparkplug_data.cpp), NCMD and DCMD (sparkplug_commands.cpp). Internal to gateway/mqtt/.
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>

#include "gateway/mqtt/sparkplug_node.h"
#include "gateway/service/access_gate.h"
#include "gateway/service/modbus_request.h"
#include "gateway/units/unit_router.h"

namespace sms::gateway {

namespace asio = boost::asio;
namespace sp = sparkplug;
namespace fc = function_code;
namespace metric_name = sparkplug_metric;
using modbus_map::RegisterEntry;

// Where the bdSeq of the latest CONNECT that may have reached the broker is kept, in state_dir.
inline constexpr std::string_view kBdSeqFile = "sparkplug-bdseq";

// Everything runs on the io thread (the router's) but stats() and the link's will and CONNECT
// callbacks (the link thread), which touch only what the members' comments say.
class SparkplugNode::Impl final : public std::enable_shared_from_this<SparkplugNode::Impl> {
 public:
  Impl(const config::Config& config, asio::io_context& io, UnitRouter& router, const RolePolicy& policy);
  void start();
  void stop();
  SparkplugStats stats() const;
  void deliver(std::uint64_t serial, Bytes response_pdu);

  // A Modbus answer: registers or bits, or the exception code and why.
  struct Answer {
    Bytes pdu;
    std::string refusal;  // the role gate's words when it refused it (it never reached the router)

    bool ok() const { return pdu.size() >= 2 && (pdu[0] & function_code::kExceptionBit) == 0; }
    std::string error_text() const;
    std::vector<std::uint16_t> registers() const;
    bool bit(std::size_t index) const;
  };

  // A table field as a metric: its register value as the client sees it (two's complement for
  // signed fields), the datatype it is born with (the register as a PLC reads it), the metric.
  static std::int64_t field_value(const modbus_map::RegisterEntry& entry, std::uint16_t reg);
  static sparkplug::DataType field_type(const modbus_map::RegisterEntry& entry);
  static sparkplug::Metric field_metric(const std::string& name, const modbus_map::RegisterEntry& entry,
                                        std::optional<std::int64_t> value);
  static std::uint64_t epoch_ms();
  std::string refusal_text(std::size_t index, const Answer& answer) const;  // of devices_[index]

 private:
  // Where the router's answers go. A Reply keeps its target alive for as long as the work runs
  // (a bus completion may come after the node is gone): that target is this small forwarder, not
  // the node, so the node (and its timer) never outlives the io_context it was made on.
  class Replies final : public Reply::Target {
   public:
    explicit Replies(std::weak_ptr<Impl> node) : node_(std::move(node)) {}
    void deliver(std::uint64_t serial, Bytes response_pdu) override {
      if (auto node = node_.lock()) node->deliver(serial, std::move(response_pdu));
    }

   private:
    std::weak_ptr<Impl> node_;
  };

  struct MetricSlot {
    std::string name;
    const RegisterEntry* entry = nullptr;
    bool from_cache = false;  // FC04 (poll cache); else FC03 (live), read at birth and after writes
    std::uint32_t deadband = 0;
    std::optional<std::int64_t> value;  // as last published
  };

  struct Device {
    std::uint8_t unit_id = 0;
    std::string id;
    const ServoUnit* unit = nullptr;
    std::vector<MetricSlot> metrics;
    std::optional<ReadRegistersRequest> cache_read;  // one FC04 over every cached metric
    std::vector<ReadRegistersRequest> live_reads;    // FC03 runs over the others
    bool born = false;
    bool busy = false;  // a read of this device is under way
    std::uint16_t status = 0;
    std::string last_command;
    std::chrono::steady_clock::time_point reported;
  };

  struct Command {
    std::optional<std::size_t> device;  // nullopt: a node command
    sp::Metric metric;
  };

  // sparkplug_node.cpp: a Modbus client of the router
  void ask(std::uint8_t unit_id, const Request& request, std::function<void(const Answer&)> done);
  void read_all(std::uint8_t unit_id, std::vector<ReadRegistersRequest> reads, std::vector<Answer> answers,
                std::function<void(std::vector<Answer>)> done);

  // sparkplug_session.cpp: the MQTT session and its bdSeq
  std::string topic(sp::MessageType type, const std::string& device = "") const;
  void load_bd_seq();
  MqttWill next_will();
  MqttWill death(std::uint64_t bd_seq) const;
  void publish(sp::MessageType type, sp::Payload payload, const std::string& device = "");
  void on_connected();
  void on_disconnected();
  void node_birth();
  void on_host_state(const Bytes& bytes);

  // sparkplug_births.cpp: births and deaths
  Device make_device(const config::ServoConfig& servo, const ServoUnit& unit);
  void publish_node_birth();
  void birth(std::size_t index, const std::vector<std::uint16_t>& facts);
  void store(Device& device, const ReadRegistersRequest& read, const std::vector<std::uint16_t>& registers);
  void append_facts(sp::Payload& payload, Device& device, const std::vector<std::uint16_t>& facts, bool everything);
  void publish_device_death(Device& device);
  void set_online_count();

  // sparkplug_data.cpp: what is published between births
  void schedule();
  void tick();
  void read_node_state();
  void check_device(std::size_t index, std::chrono::steady_clock::time_point now);
  void data(std::size_t index, std::vector<std::uint16_t> facts, std::chrono::steady_clock::time_point now);
  void publish_data(Device& device, const std::vector<std::uint16_t>& facts, const std::vector<std::size_t>& changed,
                    bool report_all);
  static std::uint64_t acquisition_time(std::uint16_t age_ms);

  // sparkplug_commands.cpp: NCMD and DCMD
  void on_message(const std::string& topic_text, const Bytes& bytes);
  sp::DataType birth_type(std::optional<std::size_t> device, std::string_view name) const;
  void bad_message(const std::string& text);
  void run_next_command();
  void run_device_command(std::size_t index, const sp::Metric& metric);
  void read_back(std::size_t index, std::size_t slot_index, std::int64_t written, const std::string& what);
  void finish_command(std::size_t index, const std::string& name, const std::string& refusal,
                      const std::string& done = "", bool report_value = false);
  void run_node_command(const sp::Metric& metric);
  void finish_node_command(const std::string& name, const std::string& refusal);
  void refuse_command(std::optional<std::size_t> device, const std::string& name, const std::string& why);

  const config::Config& config_;
  const config::MqttConfig& settings_;
  asio::io_context& io_;
  UnitRouter& router_;
  AccessGate gate_;  // the hosts' commands, as mqtt.role; counted among the refused commands
  asio::steady_timer timer_;
  std::unique_ptr<MqttLink> link_;
  std::shared_ptr<Replies> replies_;
  std::vector<Device> devices_;
  std::vector<std::string> heartbeats_;
  // Their values as holding 1000 + n of the gateway unit reads them (0 until a client writes one).
  std::vector<std::uint16_t> heartbeat_values_;
  std::unordered_map<std::uint64_t, std::function<void(const Answer&)>> pending_;
  std::uint64_t next_serial_ = 1;
  std::deque<Command> commands_;
  bool command_running_ = false;
  bool connected_ = false;                       // an MQTT session is up
  bool session_ = false;                         // connected and NBIRTH sent
  std::optional<std::uint64_t> host_timestamp_;  // of the primary host's latest STATE
  bool estop_ = false;
  bool tripped_ = false;
  std::uint16_t stops_owed_ = 0;
  bool not_persisted_ = false;
  std::uint64_t seq_ = 0;
  std::atomic<std::uint64_t> bd_seq_{0};  // of this session's CONNECT (its NBIRTH's)
  // Link thread only: the bdSeq of the next CONNECT, whether a CONNECT used it, the file.
  std::uint64_t candidate_bd_seq_ = 0;
  bool candidate_used_ = false;
  std::string bd_seq_path_;  // empty: kept in memory only
  std::optional<std::uint64_t> stored_bd_seq_;
  bool bd_seq_store_failing_ = false;
  std::atomic<bool> stopping_{false};
  mutable std::mutex stats_mutex_;
  SparkplugStats stats_;
};

}  // namespace sms::gateway
