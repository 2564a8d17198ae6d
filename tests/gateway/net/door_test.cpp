// The door's rules on their own (gateway/net/door.h): who makes room for a newcomer, the
// first-request deadline, the served budget; guests are plain objects that record being closed.
// The listeners themselves are tried against it end to end in tests/e2e/front_door_test.cpp.
#include "gateway/net/door.h"

#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>

namespace sms::gateway {
namespace {

using namespace std::chrono_literals;

// A connection as the door sees it: closes itself at the door's word, leaving as a session does.
class Guest final : public DoorGuest {
 public:
  Guest(Door& door, std::string address, bool silent) : door_(door), address_(std::move(address)), silent_(silent) {}
  void close_by_door() override {
    closed = true;
    door_.leave(ticket);
  }
  bool silent() const override { return silent_; }
  const std::string& peer() const override { return address_; }

  Door::Ticket ticket = 0;
  bool closed = false;

 private:
  Door& door_;
  std::string address_;
  bool silent_;
};

class DoorTest : public ::testing::Test {
 protected:
  DoorSettings settings(std::size_t served, std::size_t waiting, std::size_t per_address,
                        std::chrono::milliseconds deadline = 0ms) {
    return {"test",
            "test",
            "complete first request",
            DoorLimits{served, waiting, per_address, deadline},
            fixed_limit_names("the test"),
            nullptr};
  }

  // A guest let in (the test fails when the door refuses it).
  std::shared_ptr<Guest> arrive(Door& door, const std::string& address, bool silent = false) {
    auto guest = std::make_shared<Guest>(door, address, silent);
    const auto ticket = door.admit(address, guest);
    EXPECT_TRUE(ticket) << address << " refused";
    if (ticket) guest->ticket = *ticket;
    guests_.push_back(guest);
    return guest;
  }

  boost::asio::io_context io_;
  std::vector<std::shared_ptr<Guest>> guests_;
};

TEST_F(DoorTest, ASilentConnectionMakesRoomBeforeAnyThatSpoke) {
  Door door(io_, settings(8, 3, 3));
  const auto spoke_first = arrive(door, "10.0.0.1");
  const auto silent = arrive(door, "10.0.0.2", true);
  const auto spoke_later = arrive(door, "10.0.0.3");
  arrive(door, "10.0.0.4");
  EXPECT_TRUE(silent->closed);
  EXPECT_FALSE(spoke_first->closed);
  EXPECT_FALSE(spoke_later->closed);
  EXPECT_EQ(door.stats().closed_for(DoorClose::Evicted), 1u);
  EXPECT_EQ(door.stats().waiting, 3u);
}

TEST_F(DoorTest, AFloodMakesRoomFromItsOwnAddressNotFromAClientThatCameAlone) {
  Door door(io_, settings(8, 4, 4));
  const auto alone = arrive(door, "10.0.0.1");  // the oldest of all
  std::vector<std::shared_ptr<Guest>> flood;
  for (int i = 0; i < 10; ++i) flood.push_back(arrive(door, "10.0.0.66"));
  EXPECT_FALSE(alone->closed);
  // The flood's per-address budget (4) and the listener's (4, the client included) both took
  // from the flood, oldest first.
  for (int i = 0; i < 7; ++i) EXPECT_TRUE(flood[i]->closed) << i;
  for (int i = 7; i < 10; ++i) EXPECT_FALSE(flood[i]->closed) << i;
}

// A flood from many addresses, one connection each: every address holds as many, so the
// connection that waited longest gives way, never the one whose address sorts first. A client at
// 127.0.0.1 that came after the flood's connections keeps its place while older ones are there;
// the flood churns among itself.
TEST_F(DoorTest, AFloodFromManyAddressesChurnsAmongItselfWhateverTheAddressesSortLike) {
  constexpr int kFlood = 50;
  Door door(io_, settings(8, kFlood + 1, 4));
  std::vector<std::shared_ptr<Guest>> flood;
  for (int i = 0; i < kFlood; ++i) flood.push_back(arrive(door, "127.0.0." + std::to_string(i + 2)));
  const auto probe = arrive(door, "127.0.0.1");  // sorts first, came last
  for (int i = 0; i < kFlood; ++i) {
    arrive(door, "127.0.1." + std::to_string(i + 2));
    EXPECT_FALSE(probe->closed) << "newcomer " << i << " closed the probe while the flood's older ones waited";
    EXPECT_TRUE(flood[static_cast<std::size_t>(i)]->closed) << "the oldest of the flood gives way first: " << i;
  }
  // Now the probe is the oldest: the next newcomer closes it, by age, as it would any other.
  arrive(door, "127.0.2.1");
  EXPECT_TRUE(probe->closed);
}

TEST_F(DoorTest, AnAddressAtItsBudgetMakesRoomFromItself) {
  Door door(io_, settings(8, 16, 2));
  const auto a1 = arrive(door, "10.0.0.1");
  const auto a2 = arrive(door, "10.0.0.1");
  const auto b1 = arrive(door, "10.0.0.2");
  arrive(door, "10.0.0.1");
  EXPECT_TRUE(a1->closed);
  EXPECT_FALSE(a2->closed);
  EXPECT_FALSE(b1->closed);
}

TEST_F(DoorTest, TrustedConnectionsAreNeverEvictedAndTheServedBudgetRefuses) {
  Door door(io_, settings(2, 1, 1));
  const auto first = arrive(door, "10.0.0.1");
  ASSERT_TRUE(door.trust(first->ticket));
  const auto second = arrive(door, "10.0.0.1");
  arrive(door, "10.0.0.1");  // takes the waiting place of `second`
  EXPECT_TRUE(second->closed);
  EXPECT_FALSE(first->closed);
  const auto third = guests_.back();
  ASSERT_TRUE(door.trust(third->ticket));
  EXPECT_EQ(door.stats().served, 2u);
  // Served budget full: refused at the door, counted.
  auto refused = std::make_shared<Guest>(door, "10.0.0.9", false);
  EXPECT_FALSE(door.admit("10.0.0.9", refused));
  EXPECT_EQ(door.stats().closed_for(DoorClose::Full), 1u);
  door.leave(first->ticket);
  EXPECT_EQ(door.stats().served, 1u);
  EXPECT_TRUE(door.admit("10.0.0.9", refused));
}

TEST_F(DoorTest, AWaitingConnectionThatBecomesServedOverTheBudgetIsRefused) {
  Door door(io_, settings(1, 4, 4));
  const auto a = arrive(door, "10.0.0.1");
  const auto b = arrive(door, "10.0.0.2");
  ASSERT_TRUE(door.trust(a->ticket));
  EXPECT_FALSE(door.trust(b->ticket));
  EXPECT_EQ(door.stats().closed_for(DoorClose::Full), 1u);
}

TEST_F(DoorTest, NoCompleteFirstRequestByTheDeadlineIsClosedAndCounted) {
  Door door(io_, settings(8, 8, 8, 50ms));
  const auto slow = arrive(door, "10.0.0.1");
  const auto quick = arrive(door, "10.0.0.2");
  door.heard(quick->ticket);  // its request came: no deadline, though not trusted yet
  io_.run_for(2s);            // the door's timer is the only work: run() ends once it fired
  EXPECT_TRUE(slow->closed);
  EXPECT_FALSE(quick->closed);
  EXPECT_EQ(door.stats().closed_for(DoorClose::Deadline), 1u);
  EXPECT_EQ(door.stats().waiting, 1u);
}

TEST_F(DoorTest, DescribesItsLimitsForTheStartLine) {
  Door door(io_, settings(32, 16, 4, 10s));
  EXPECT_EQ(door.describe(),
            "at most 32 connections served; at most 16 waiting for a complete first request, 4 per client address, "
            "each within 10 s");
}

}  // namespace
}  // namespace sms::gateway
