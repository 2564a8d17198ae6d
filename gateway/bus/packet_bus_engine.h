#pragma once
// The bus engine for the two packet protocols, feetech `FF FF` and d55d `D5 5D` (SPEC §1.1,
// §1.2): one code path, parameterised by protocol::PacketFormat and a row of protocol rules
// (which ERROR bits mean "refused", whether SYNC READ exists).
//
// How a transaction runs (SPEC §1.1 "host practice"):
// - flush the input, transmit, then wait for the answer until a deadline sized from the
//   request's and the reply's wire time plus the bus's response timeout;
// - the decoder hunts for the header and resynchronises after garbage; only a frame from the
//   addressed ID with the expected shape is the answer — a late reply from another servo, or a
//   reply of another length, is counted as stray and waited past; a frame identical to the
//   request (an adapter's echo) is taken only if nothing else comes;
// - the answer to every unicast WRITE is consumed before the next transmit; broadcasts (ACTION,
//   SYNC WRITE, writes to a servo that does not answer writes) complete once drained from the
//   port and their wire time has passed;
// - no valid answer: retry up to `retries` times; then Timeout, or Corrupt when damaged frames
//   were all that came back.
//
// Decision (refusals, MODBUS_MAP.md 0x04): the refusal bits are d55d's instruction (bit 5) and
// checksum (bit 4) error bits; checksum alone means our frame arrived damaged, so the frame
// is sent again first. Feetech `sts`/`sms1` have no instruction-error bit; their firmware sets
// bit 4 ("angle", also "instruction out of range") in the answer to a write it does not take,
// so bit 4 is feetech's refusal bit. A refusal bit counts only where the answer cannot be
// anything else: in the answer to WRITE / REG WRITE, and in an answer to READ that lacks its
// data. An answer carrying the data asked for, and every PING answer, is an answer: its ERROR
// bits are status (recorded as the servo's last status byte), not an error.
//
// Decision (offline servos): a client operation addressed to a servo the poller has marked
// offline fails at once with Timeout (-> 0x0B) without touching the bus, so a client polling a
// dead servo cannot make the bus pay timeouts; the servo's probe brings it back within one
// probe period.
#include <memory>

#include "gateway/bus/bus_engine.h"

namespace sms::gateway {

class PacketBusEngine final : public BusEngine {
 public:
  // Throws std::invalid_argument for settings it cannot run (see make_bus_engine).
  explicit PacketBusEngine(BusSettings settings);
  ~PacketBusEngine() override;

  void start() override;
  void stop() override;
  void submit(BusOp op, Priority priority, Completion done) override;

  const BusSettings& settings() const override;
  bool bus_up() const override;
  BusCountersSnapshot counters() const override;
  const PollCache& cache() const override;
  bool discovered() const override;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::gateway
