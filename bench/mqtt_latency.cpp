// mqtt_latency: the Sparkplug B northbound under motion. A real Mosquitto broker
// (/usr/sbin/mosquitto) on a free loopback port, the real sms-gateway as a child process with an
// mqtt section, N simulated sts servos at 1 000 000 baud (wire timing on) that a Modbus client
// keeps moving, and a Sparkplug host (libmosquitto) subscribed to spBv1.0/#.
//
//   mqtt_latency [--seconds 5] [--servos 6] [--data-period-ms 10]
//
// Printed: DDATA messages and metrics per second; poll -> host latency (the metric's timestamp is
// the poll's time, so this is cache -> node -> broker -> host; ms resolution); write -> first
// DDATA that shows the servo moving (Modbus FC06 of the goal until the host sees the new
// position: poll period + data period + MQTT); the broker's CPU is not separated.
#include <modbus/modbus.h>
#include <mosquitto.h>

#include <fcntl.h>

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <thread>

#include "bench/bench_support.h"
#include "protocol/sparkplug/sparkplug.h"

namespace {

using namespace sms::bench;
using namespace std::chrono_literals;
namespace sp = sms::sparkplug;

constexpr int kGoalPosition = 42;
constexpr int kTorqueEnable = 40;

std::uint64_t epoch_us() {
  return static_cast<std::uint64_t>(
      std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::system_clock::now().time_since_epoch())
          .count());
}

struct Observed {
  std::mutex mutex;
  std::uint64_t ddata = 0;
  std::uint64_t metrics = 0;
  std::size_t births = 0;
  std::vector<std::uint32_t> poll_to_host_ns;
  // Per device: the position last seen, and when a move was commanded (0: none pending).
  std::map<std::string, std::int64_t> position;
  std::map<std::string, std::uint64_t> commanded_us;
  std::vector<std::uint32_t> write_to_host_ns;
};

}  // namespace

int main(int argc, char** argv) {
  double seconds = 5, servos = 6, data_period_ms = 10;
  if (const auto exit_status = parse_arguments(argc, argv, "Sparkplug B messages/s and latency while servos move",
                                               {{"seconds", &seconds, "how long the servos move"},
                                                {"servos", &servos, "sts servos on the bus (1..20)"},
                                                {"data-period-ms", &data_period_ms, "mqtt.data_period_ms"}})) {
    return *exit_status;
  }
  try {
    quiet_logs();
    const auto count = static_cast<unsigned>(std::clamp(servos, 1.0, 20.0));
    sms::test::TempDir broker_dir;
    sms::test::MosquittoBroker broker(broker_dir);
    sms::simulator::SimulatedBus bus(sts_bus(count));
    start_precise(bus);
    GatewaySetup setup;
    setup.device = bus.slave_path();
    setup.servos = count;
    setup.extra_yaml =
        "mqtt: {broker: \"127.0.0.1:" + std::to_string(broker.port()) +
        "\", group_id: bench, edge_node_id: gw, data_period_ms: " + std::to_string(static_cast<int>(data_period_ms)) +
        "}\n";

    Observed observed;
    mosquitto_lib_init();
    mosquitto* host = mosquitto_new(nullptr, true, &observed);
    mosquitto_message_callback_set(host, [](mosquitto*, void* data, const mosquitto_message* message) {
      const std::uint64_t now = epoch_us();
      auto& seen = *static_cast<Observed*>(data);
      const auto topic = sp::parse_topic(message->topic);
      if (!topic) return;
      const auto payload = sp::decode(std::span<const std::uint8_t>(static_cast<const std::uint8_t*>(message->payload),
                                                                    static_cast<std::size_t>(message->payloadlen)));
      if (!payload) return;
      std::lock_guard lock(seen.mutex);
      if (topic->type == sp::MessageType::DBirth) ++seen.births;
      if (topic->type != sp::MessageType::DData) return;
      ++seen.ddata;
      seen.metrics += payload->metrics.size();
      for (const auto& metric : payload->metrics) {
        if (metric.name != "present_position" || !metric.timestamp) continue;
        // The timestamp has ms resolution: count from the middle of its millisecond.
        const std::uint64_t polled_us = *metric.timestamp * 1000 + 500;
        if (now > polled_us) seen.poll_to_host_ns.push_back(static_cast<std::uint32_t>((now - polled_us) * 1000));
        const auto value = sp::integer_value(metric.value).value_or(0);
        auto& commanded = seen.commanded_us[topic->device];
        if (commanded != 0 && value != seen.position[topic->device]) {
          seen.write_to_host_ns.push_back(static_cast<std::uint32_t>((now - commanded) * 1000));
          commanded = 0;
        }
        seen.position[topic->device] = value;
      }
    });
    if (mosquitto_connect(host, "127.0.0.1", broker.port(), 30) != MOSQ_ERR_SUCCESS) {
      throw std::runtime_error("cannot connect to the bench broker");
    }
    mosquitto_subscribe(host, nullptr, "spBv1.0/#", 0);
    mosquitto_loop_start(host);

    BenchGateway gateway(setup);
    gateway.wait_ready(count);
    sms::test::await_or_throw(
        [&] {
          std::lock_guard lock(observed.mutex);
          return observed.births >= count;
        },
        "a DBIRTH of every device at the bench's Sparkplug host");
    ModbusClient modbus(gateway.port(), 1);
    for (unsigned unit = 1; unit <= count; ++unit) {
      modbus.set_unit(static_cast<int>(unit));
      modbus_write_register(modbus.context(), kTorqueEnable, 1);
    }
    {
      std::lock_guard lock(observed.mutex);  // measure the motion only, not the births
      observed.ddata = observed.metrics = 0;
      observed.poll_to_host_ns.clear();
    }
    // Every 250 ms each servo gets a new goal (alternating 1000 / 3000 steps).
    const auto start = Clock::now();
    const auto duration = std::chrono::milliseconds(static_cast<long>(seconds * 1000));
    for (int step = 0; Clock::now() - start < duration; ++step) {
      for (unsigned unit = 1; unit <= count; ++unit) {
        modbus.set_unit(static_cast<int>(unit));
        {
          std::lock_guard lock(observed.mutex);
          observed.commanded_us["unit-" + std::to_string(unit)] = epoch_us();
        }
        modbus_write_register(modbus.context(), kGoalPosition, step % 2 == 0 ? 3000 : 1000);
      }
      std::this_thread::sleep_for(250ms);
    }
    const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
    mosquitto_disconnect(host);
    mosquitto_loop_stop(host, true);
    mosquitto_destroy(host);

    std::lock_guard lock(observed.mutex);
    print_note(std::to_string(count) + " sts servos moving, poll period 20 ms, data period " +
               std::to_string(static_cast<int>(data_period_ms)) + " ms, " + std::to_string(elapsed) + " s");
    print_figure("mqtt.ddata_per_s", static_cast<double>(observed.ddata) / elapsed, "msg/s");
    print_figure("mqtt.metrics_per_s", static_cast<double>(observed.metrics) / elapsed, "metrics/s");
    const auto poll = summarize(observed.poll_to_host_ns);
    print_latency("mqtt.poll_to_host", poll, LatencyUnit::Ms);
    const auto write = summarize(observed.write_to_host_ns);
    print_latency("mqtt.write_to_first_move", write, LatencyUnit::Ms, false);
    print_figure("mqtt.write_to_first_move.count", static_cast<double>(write.count), "moves");
    return gateway.stop() == 0 ? 0 : 1;
  } catch (const std::exception& error) {
    std::cerr << "mqtt_latency: " << error.what() << "\n";
    return 1;
  }
}
