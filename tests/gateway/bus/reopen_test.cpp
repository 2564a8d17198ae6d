// A bus whose port disappears goes down, fails what was queued with BusDown, and comes back
// by itself when the device reappears; a device missing at start is waited for the same way.
// The simulator's `link` option plays the re-plugged adapter: the same path, a new pty.
#include <gtest/gtest.h>
#include <unistd.h>

#include <string>

#include "gateway/bus/packet_transactor.h"
#include "tests/support/bus_test_support.h"

namespace sms::gateway {
namespace {

using namespace testing;
using protocol::Bytes;

std::string link_path(const char* what) {
  return "/tmp/sms-gateway-" + std::string(what) + "-" + std::to_string(::getpid());
}

simulator::BusOptions linked_servos(const std::string& link) {
  simulator::BusOptions options = simulated_servos({1, 2});
  options.link = link;
  return options;
}

TEST(BusReopen, BusGoesDownWhenThePtyDisappearsAndUpWhenItComesBack) {
  LogCapture log;
  const std::string link = link_path("reopen");
  auto simulator = std::make_unique<simulator::SimulatedBus>(linked_servos(link));
  simulator->start();
  auto engine = make_bus_engine(bus_settings(link, {1, 2}));
  engine->start();
  ASSERT_TRUE(eventually([&] { return engine->discovered() && engine->cache().online_count() == 2; }));

  simulator->stop();  // the pty master closes: EIO on the engine's side
  ASSERT_TRUE(eventually([&] { return !engine->bus_up(); }));
  EXPECT_EQ(engine->counters().bus_down_events, 1U);
  EXPECT_EQ(engine->cache().online_count(), 0U);
  EXPECT_TRUE(log.contains("bus test: ")) << log.text();
  EXPECT_TRUE(log.contains("bus down; reopening every 50 ms")) << log.text();

  bool refused_inside_submit = false;
  engine->submit(ReadOp{1, 5, 1}, Priority::ClientRead, [&](BusResult result) {
    refused_inside_submit = true;
    EXPECT_EQ(result.status, BusStatus::BusDown);
    EXPECT_NE(result.detail.find(link), std::string::npos) << result.detail;
  });
  EXPECT_TRUE(refused_inside_submit);

  simulator = std::make_unique<simulator::SimulatedBus>(linked_servos(link));
  simulator->start();
  ASSERT_TRUE(eventually([&] { return engine->bus_up() && engine->discovered(); }));
  const BusResult result = transact(*engine, ReadOp{2, 5, 1}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x02}));
  ASSERT_TRUE(eventually([&] { return engine->cache().online_count() == 2; }));
  engine->stop();
  simulator->stop();
}

TEST(BusReopen, OperationInFlightWhenThePortIsLostEndsBusDown) {
  const std::string link = link_path("inflight");
  auto simulator = std::make_unique<simulator::SimulatedBus>(linked_servos(link));
  simulator->start();
  BusSettings settings = bus_settings(link, {1, 2});
  settings.poll = false;
  settings.response_timeout = 1000ms;
  auto engine = make_bus_engine(settings);
  engine->start();
  ASSERT_TRUE(eventually([&] { return engine->discovered(); }));
  simulator->set_reply_delay(1, 500ms);
  const auto requests_before = simulator->stats().requests;
  std::promise<BusResult> promise;
  engine->submit(ReadOp{1, 5, 1}, Priority::ClientRead,
                 [&](BusResult result) { promise.set_value(std::move(result)); });
  ASSERT_TRUE(eventually([&] { return simulator->stats().requests > requests_before; }));
  simulator->stop();
  auto future = promise.get_future();
  ASSERT_EQ(future.wait_for(2s), std::future_status::ready);
  EXPECT_EQ(future.get().status, BusStatus::BusDown);
  engine->stop();
}

TEST(BusReopen, DeviceMissingAtStartIsReportedAndWaitedFor) {
  LogCapture log;
  const std::string link = link_path("late");
  ::unlink(link.c_str());
  auto engine = make_bus_engine(bus_settings(link, {1, 2}));
  engine->start();
  EXPECT_FALSE(engine->bus_up());
  EXPECT_TRUE(log.contains("cannot open serial device " + link)) << log.text();
  EXPECT_TRUE(log.contains("does not exist")) << log.text();
  EXPECT_TRUE(log.contains("retrying every 50 ms")) << log.text();

  simulator::SimulatedBus simulator(linked_servos(link));
  simulator.start();
  ASSERT_TRUE(eventually([&] { return engine->bus_up() && engine->cache().online_count() == 2; }));
  const BusResult result = transact(*engine, ReadOp{1, 5, 1}, Priority::ClientRead);
  ASSERT_EQ(result.status, BusStatus::Ok) << result.detail;
  EXPECT_EQ(result.data, (Bytes{0x01}));
  engine->stop();
}

// Lending the line (the console's commissioning of a bus's own line): the engine lets go of the
// port at a transaction boundary and stays off it — the simulator's request count is the
// witness, and another opener can talk to the servos — refusing client work with the reason;
// a safe stop owed to a silent servo waits for the line's return and is the first thing sent
// to it then.
TEST(BusLend, LentLineIsLeftAloneUntilTakenBackAndOwedStopsComeFirstThen) {
  const std::string link = link_path("lend");
  auto simulator = std::make_unique<simulator::SimulatedBus>(linked_servos(link));
  simulator->start();
  auto engine = make_bus_engine(bus_settings(link, {1, 2}));
  engine->start();
  ASSERT_TRUE(eventually([&] { return engine->discovered() && engine->cache().online_count() == 2; }));
  constexpr std::uint16_t kTorqueEnable = 40;  // sts
  ASSERT_TRUE(simulator->write_memory(2, kTorqueEnable, Bytes{1}));
  simulator->set_offline(2, true);  // the fault: servo 2 is silent when its stop is due
  engine->owe_stop(OwedStop{WriteOp{2, kTorqueEnable, Bytes{0}}, "test stop"});

  ASSERT_TRUE(engine->lend_line("lent to the test", 2s));
  EXPECT_TRUE(engine->line_lent());
  EXPECT_FALSE(engine->bus_up());
  EXPECT_EQ(engine->cache().online_count(), 0U);
  EXPECT_EQ(engine->owed_stop_count(), 1U);
  BusResult refused = transact(*engine, ReadOp{1, 5, 1}, Priority::ClientRead);
  EXPECT_EQ(refused.status, BusStatus::BusDown);
  EXPECT_NE(refused.detail.find("lent to the test"), std::string::npos) << refused.detail;

  // Nobody but the borrower on the line: the engine sends nothing (it polled every 10 ms).
  simulator->set_offline(2, false);
  const auto requests_before = simulator->stats().requests;
  std::this_thread::sleep_for(300ms);
  EXPECT_EQ(simulator->stats().requests, requests_before);
  {
    BusCounters counters;
    PacketTransactor borrower(protocol::BusProtocol::Feetech, SerialSettings{link, 1'000'000}, {50ms, "borrower: "},
                              counters);
    ASSERT_TRUE(borrower.open());
    TransactionEvents events;  // nothing to learn here
    const BusResult pinged = borrower.execute(borrower.ping_request(1, 3), events);
    EXPECT_EQ(pinged.status, BusStatus::Ok) << pinged.detail;
    borrower.close();
  }
  EXPECT_EQ(simulator->read_field(2, "torque_enable"), 1) << "the owed stop went out while the line was lent";

  // Taken back and lent again at once (the bus thread may not have reopened meanwhile): the
  // second lend is confirmed too.
  ASSERT_TRUE(engine->take_back_line());
  ASSERT_TRUE(engine->lend_line("lent again", 2s));
  EXPECT_TRUE(engine->line_lent());
  ASSERT_TRUE(engine->take_back_line());
  EXPECT_FALSE(engine->take_back_line());
  ASSERT_TRUE(eventually([&] { return engine->bus_up() && engine->discovered(); }));
  EXPECT_FALSE(engine->line_lent());
  ASSERT_TRUE(eventually([&] { return simulator->read_field(2, "torque_enable") == 0; }));
  ASSERT_TRUE(eventually([&] { return engine->owed_stop_count() == 0 && engine->cache().online_count() == 2; }));
  engine->stop();
  simulator->stop();
}

}  // namespace
}  // namespace sms::gateway
