#include "gateway/units/no_jump.h"

#include <memory>

#include <spdlog/spdlog.h>

namespace sms::gateway {

void hold_before_enable(std::vector<HoldTarget> targets, const PostFn& post,
                        const std::function<void(std::optional<BusResult>)>& done) {
  struct Read {
    std::size_t target;
    modbus_map::BusRange range;
  };
  auto shared = std::make_shared<std::vector<HoldTarget>>(std::move(targets));
  auto reads = std::make_shared<std::vector<Read>>();
  auto ranges = std::make_shared<std::vector<std::vector<modbus_map::BusRange>>>();
  for (std::size_t t = 0; t < shared->size(); ++t) {
    ranges->push_back(modbus_map::enable_context_reads(*(*shared)[t].spec));
    for (const auto& range : ranges->back()) reads->push_back(Read{t, range});
  }
  if (reads->empty()) {
    done(std::nullopt);
    return;
  }
  auto write_holds = [shared, reads, ranges, post, done](std::vector<BusResult> results) {
    if (const BusResult* failure = BusJoin::first_failure(results)) {
      done(*failure);
      return;
    }
    struct Hold {
      std::size_t target;
      modbus_map::BusWrite write;
    };
    std::vector<Hold> holds;
    std::size_t next = 0;
    for (std::size_t t = 0; t < shared->size(); ++t) {
      const HoldTarget& target = (*shared)[t];
      std::vector<protocol::Bytes> data;
      for (std::size_t r = 0; r < (*ranges)[t].size(); ++r) data.push_back(std::move(results[next++].data));
      const modbus_map::StopContext context{(*ranges)[t], data};
      const auto hold = modbus_map::plan_enable_hold(*target.spec, target.order, context, target.writes);
      if (!hold) {
        done(BusResult{BusStatus::ServoRefused, 0, {}, target.label + ": enabling write refused: " + hold.error()});
        return;
      }
      if (!*hold) {
        spdlog::debug("safety: {}: no hold before the write (it enables nothing, or the servo already drives)",
                      target.label);
        continue;
      }
      spdlog::debug("safety: {}: {} first", target.label, (*hold)->what);
      for (const auto& write : (*hold)->writes) holds.push_back(Hold{t, write});
    }
    if (holds.empty()) {
      done(std::nullopt);
      return;
    }
    auto join = BusJoin::create(holds.size(), post, [done](const std::vector<BusResult>& written) {
      const BusResult* failure = BusJoin::first_failure(written);
      done(failure ? std::optional<BusResult>(*failure) : std::nullopt);
    });
    for (std::size_t i = 0; i < holds.size(); ++i) {
      const HoldTarget& target = (*shared)[holds[i].target];
      target.engine->submit(WriteOp{target.servo_id, holds[i].write.address, std::move(holds[i].write.data), false,
                                    target.expect_reply, target.epoch},
                            Priority::ClientWrite, join->completion(i));
    }
  };
  auto join = BusJoin::create(reads->size(), post, std::move(write_holds));
  for (std::size_t i = 0; i < reads->size(); ++i) {
    const HoldTarget& target = (*shared)[(*reads)[i].target];
    target.engine->submit(ReadOp{target.servo_id, (*reads)[i].range.address, (*reads)[i].range.count},
                          Priority::ClientWrite, join->completion(i));
  }
}

}  // namespace sms::gateway
