#include "gateway/bus/bus_join.h"

#include <stdexcept>

namespace sms::gateway {

Completion on_io_thread(const PostFn& post, std::function<void(BusResult)> then) {
  return [post, then = std::move(then)](BusResult result) mutable {
    post([then = std::move(then), result = std::move(result)]() mutable { then(std::move(result)); });
  };
}

std::shared_ptr<BusJoin> BusJoin::create(std::size_t count, PostFn post, Done done) {
  if (count == 0) throw std::invalid_argument("BusJoin::create: nothing to join");
  return std::shared_ptr<BusJoin>(new BusJoin(count, std::move(post), std::move(done)));
}

BusJoin::BusJoin(std::size_t count, PostFn post, Done done)
    : results_(count), remaining_(count), post_(std::move(post)), done_(std::move(done)) {}

Completion BusJoin::completion(std::size_t index) {
  if (index >= results_.size()) throw std::out_of_range("BusJoin::completion: index past the operations");
  return [self = shared_from_this(), index](BusResult result) { self->complete(index, std::move(result)); };
}

void BusJoin::complete(std::size_t index, BusResult result) {
  std::vector<BusResult> all;
  {
    std::lock_guard lock(mutex_);
    results_[index] = std::move(result);
    if (--remaining_ != 0) return;
    all = std::move(results_);
  }
  post_([done = std::move(done_), all = std::move(all)]() mutable { done(std::move(all)); });
}

const BusResult* BusJoin::first_failure(const std::vector<BusResult>& results) {
  for (const auto& result : results) {
    if (result.status != BusStatus::Ok) return &result;
  }
  return nullptr;
}

}  // namespace sms::gateway
