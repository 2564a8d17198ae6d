#pragma once
// Several bus operations submitted for one Modbus request (a sync-group write spanning two
// buses, ACTION on every bus, a register range needing two READs) answered together: each
// operation's Completion lands here, from whichever bus thread, and once all have, `done`
// runs on the io thread with every result in submission order.
#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

#include "gateway/bus/bus_operations.h"

namespace sms::gateway {

// Runs a function on the Modbus TCP io thread (asio::post in the gateway, the same in tests).
using PostFn = std::function<void(std::function<void()>)>;

// Wraps one bus Completion so that it runs `then` on the io thread.
Completion on_io_thread(const PostFn& post, std::function<void(BusResult)> then);

class BusJoin : public std::enable_shared_from_this<BusJoin> {
 public:
  using Done = std::function<void(std::vector<BusResult>)>;

  // `count` >= 1 operations; call completion(i) once for each i < count.
  static std::shared_ptr<BusJoin> create(std::size_t count, PostFn post, Done done);

  Completion completion(std::size_t index);

  // The first failed result in submission order, or nullptr when all succeeded.
  static const BusResult* first_failure(const std::vector<BusResult>& results);

 private:
  BusJoin(std::size_t count, PostFn post, Done done);
  void complete(std::size_t index, BusResult result);

  std::mutex mutex_;
  std::vector<BusResult> results_;
  std::size_t remaining_;
  PostFn post_;
  Done done_;
};

}  // namespace sms::gateway
