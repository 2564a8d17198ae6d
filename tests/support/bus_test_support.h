#pragma once
// Helpers for the bus engine tests: a real SimulatedBus on a pty, an engine pointed at it,
// blocking transactions with a deadline, and a log sink to assert what was logged.
#include <gtest/gtest.h>
#include <spdlog/sinks/ringbuffer_sink.h>
#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdint>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gateway/bus/bus_engine.h"
#include "modbus_map/register_map.h"
#include "simulator/simulated_bus.h"
#include "tests/support/eventually.h"

namespace sms::gateway::testing {

using namespace std::chrono_literals;
using ::sms::test::eventually;

// The protocol a table is spoken in (docs/PROTOCOL.md §1).
inline protocol::BusProtocol protocol_of(modbus_map::TableId table) {
  switch (table) {
    case modbus_map::TableId::D55d: return protocol::BusProtocol::D55d;
    case modbus_map::TableId::Smsmb: return protocol::BusProtocol::ModbusRtu;
    default: return protocol::BusProtocol::Feetech;
  }
}

// `count` servos of one table, IDs 1..count, all at `baud`.
inline simulator::BusOptions simulated_servos(std::vector<std::uint8_t> ids,
                                              modbus_map::TableId table = modbus_map::TableId::Sts,
                                              std::uint32_t baud = 1'000'000) {
  simulator::BusOptions options;
  const auto protocol = protocol_of(table);
  for (const auto id : ids) options.servos.push_back({id, table, protocol, baud});
  options.seed = 1;  // fault injection dice: the same faults on every run
  return options;
}

// The table's feedback block, as the gateway polls it without `poll:` in the config.
inline AddressBlock feedback_block(modbus_map::TableId table) {
  const auto block = modbus_map::default_poll_block(table);
  return {block.address, block.count};
}

// Whether the machine held the simulator's bus thread `at_least` in one go, in a hold that ended
// after `since` (SimulatedBus::holds): a servo silent then was silent by the machine's doing
// (tests/README.md "Counting on a loaded machine").
inline bool simulator_held(const simulator::SimulatedBus& bus, std::chrono::steady_clock::duration at_least,
                           std::chrono::steady_clock::time_point since) {
  for (const simulator::Hold& hold : bus.holds()) {
    if (hold.ended >= since && hold.held >= at_least) return true;
  }
  return false;
}

// Settings for a bus on `device` with the servos `ids`. The response timeout is generous: on a
// loaded machine (2 cores, sanitizers) a pty and the simulator's thread add milliseconds.
inline BusSettings bus_settings(std::string device, std::vector<std::uint8_t> ids,
                                modbus_map::TableId table = modbus_map::TableId::Sts, std::uint32_t baud = 1'000'000) {
  BusSettings settings;
  settings.name = "test";
  settings.protocol = protocol_of(table);
  settings.serial.device = std::move(device);
  settings.serial.baud = baud;
  settings.response_timeout = 50ms;
  settings.retries = 2;
  settings.poll_period = 10ms;
  settings.probe_period = 200ms;
  settings.reopen_period = 50ms;
  settings.queue_depth = 64;
  const auto order =
      table == modbus_map::TableId::Smsmb ? modbus_map::ByteOrder::HighFirst : modbus_map::ByteOrder::LowFirst;
  for (const auto id : ids) settings.servos.push_back({id, table, order, feedback_block(table)});
  return settings;
}

// One engine under test, for suites run on every protocol: the table (its protocol follows),
// the rate, a RAM field the tests write (one byte, or one register) and a block to read live.
struct EngineKind {
  std::string name;
  modbus_map::TableId table;
  std::uint32_t baud;
  std::uint16_t field;
  AddressBlock read{};
  protocol::Bytes value(std::uint8_t v) const {
    return table == modbus_map::TableId::Smsmb ? protocol::Bytes{0, v} : protocol::Bytes{v};
  }
};
inline void PrintTo(const EngineKind& kind, std::ostream* out) { *out << kind.name; }

// Submits and waits for the completion (at most kAwaitTimeout, then fails the test with Cancelled).
inline BusResult transact(BusEngine& engine, BusOp op, Priority priority = Priority::ClientWrite) {
  auto promise = std::make_shared<std::promise<BusResult>>();
  auto future = promise->get_future();
  engine.submit(std::move(op), priority, [promise](BusResult result) { promise->set_value(std::move(result)); });
  if (future.wait_for(test::kAwaitTimeout) != std::future_status::ready) {
    ADD_FAILURE() << "no completion within " << test::kAwaitTimeout.count() << " ms";
    return BusResult{BusStatus::Cancelled, 0, {}, "test: no completion"};
  }
  return future.get();
}

// Replaces the default logger with one writing into memory for the lifetime of the object.
class LogCapture {
 public:
  LogCapture() : sink_(std::make_shared<spdlog::sinks::ringbuffer_sink_mt>(1000)), previous_(spdlog::default_logger()) {
    auto logger = std::make_shared<spdlog::logger>("capture", sink_);
    logger->set_level(spdlog::level::info);
    logger->set_pattern("%v");
    spdlog::set_default_logger(logger);
  }
  ~LogCapture() { spdlog::set_default_logger(previous_); }
  LogCapture(const LogCapture&) = delete;
  LogCapture& operator=(const LogCapture&) = delete;

  std::string text() const {
    std::string all;
    for (const auto& line : sink_->last_formatted()) all += line;
    return all;
  }
  bool contains(const std::string& needle) const { return text().find(needle) != std::string::npos; }

 private:
  std::shared_ptr<spdlog::sinks::ringbuffer_sink_mt> sink_;
  std::shared_ptr<spdlog::logger> previous_;
};

}  // namespace sms::gateway::testing
