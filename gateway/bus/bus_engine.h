#pragma once
// One engine per servo bus: it owns the serial port, runs bus operations strictly one at a
// time on its own thread in priority order (FIFO within a priority), polls the feedback block
// of every servo into its PollCache, discovers the servos at start and reopens a lost port by
// itself. The Modbus TCP side talks to it through submit() and cache() only (gateway/bus/bus_operations.h).
//
//   auto engine = make_bus_engine(settings);   // settings: bus_settings_for(...) or by hand
//   engine->start();
//   engine->submit(ReadOp{1, 56, 2}, Priority::ClientRead, [](BusResult r) { ... });
//   engine->cache().copy(1, 56, bytes, &state);   // input registers: no bus traffic
//
// Completions run on the bus thread, except QueueFull, BusDown while the port is down, and
// Cancelled after stop(): those run synchronously inside submit(), on the caller's thread,
// before submit() returns. Never call submit() while holding a lock the completion takes.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "config/config.h"
#include "gateway/bus/bus_counters.h"
#include "gateway/bus/bus_operations.h"
#include "gateway/bus/motion_gate.h"
#include "gateway/bus/poll_cache.h"
#include "gateway/bus/serial_port.h"
#include "modbus_map/control_table.h"
#include "protocol/bus_protocol.h"

namespace sms::gateway {

class WireMonitor;  // wire_monitor.h

struct ServoSettings {
  std::uint8_t servo_id = 1;
  modbus_map::TableId table = modbus_map::TableId::Sts;
  modbus_map::ByteOrder byte_order = modbus_map::ByteOrder::LowFirst;  // for identity values
  AddressBlock poll_block;  // feedback block polled into the cache (bus addresses)
};

struct BusSettings {
  std::string name;
  protocol::BusProtocol protocol = protocol::BusProtocol::Feetech;
  SerialSettings serial;
  // Time a servo may take to start answering beyond the frames' wire time: its return delay
  // (sts: address 7 x 2 us; d55d: address 5 x 500 us) plus the adapter's latency (an FTDI
  // adapter holds short replies up to its latency timer, 16 ms by default).
  std::chrono::milliseconds response_timeout{20};
  unsigned retries = 2;                           // attempts after the first one
  std::chrono::milliseconds poll_period{20};      // start of one cycle to the next; 0 = back to back
  std::chrono::milliseconds probe_period{1000};   // an offline servo is asked once per period
  std::chrono::milliseconds reopen_period{1000};  // a lost or missing port is retried this often
  std::size_t queue_depth = 64;                   // client operations waiting, all priorities
  bool discover = true;                           // PING and identity READs before polling starts
  bool poll = true;                               // cyclic polling into the cache (off: live operations only)
  std::vector<ServoSettings> servos;
  // The safety rules' gate for this bus's motion writes (docs/PLC_GUIDE.md "Safety"); empty: none.
  std::shared_ptr<const MotionGate> motion_gate;
  // The bus monitor the line's traffic is recorded in (wire_monitor.h); empty: none.
  std::shared_ptr<WireMonitor> wire_monitor;
};

struct OwedStop {
  WriteOp write;    // the servo (write.servo_id) and what stops it without knowing its state
  std::string why;  // "e-stop", "watchdog", ... for the log
};
class BusEngine {
 public:
  virtual ~BusEngine() = default;

  // Opens the port (a missing port is logged and retried: the bus starts down), starts the
  // bus thread, runs discovery, then polls. Call once.
  virtual void start() = 0;
  // Fails what is queued with Cancelled, closes the port, joins the thread. Idempotent.
  virtual void stop() = 0;

  // Queues one operation; see the header comment for where `done` runs. Throws
  // std::invalid_argument for an operation this bus cannot express (e.g. RawPduOp on a packet
  // bus, a READ of the broadcast ID, a count beyond the packet limits): a programming error.
  virtual void submit(BusOp op, Priority priority, Completion done) = 0;

  // A safe stop that could not be delivered (bus down, servo offline or silent) is owed
  // (docs/PLC_GUIDE.md "Safety"): the engine keeps `stop.write` (the servo's torque off) and sends it the
  // moment it can reach the servo — first thing after the port (re)opens, in place of the servo's
  // probe while it is offline, before any other work — every probe period until the servo
  // acknowledges it, or, for a servo that does not answer writes, until a read shows the value.
  // Until then motion writes to that servo (and broadcast motion on the bus) are refused
  // (MotionBlocked). A later owe_stop() for the same servo replaces the earlier one.
  virtual void owe_stop(OwedStop stop) = 0;
  // How many servos are owed a stop right now (lock-free: read on every gateway-unit read).
  virtual std::size_t owed_stop_count() const = 0;
  // The stops owed right now, in servo order: what the safety state file keeps across a restart
  // (docs/SAFETY.md "What survives a restart"; restored through owe_stop() before start()).
  virtual std::vector<OwedStop> owed_stops() const = 0;
  // `changed` runs after every change of the owed stops — a servo becomes owed (owe_stop) or
  // takes its stop — on the thread that made the change, outside the engine's other locks; it
  // must be quick and must not call on_owed_stops_changed(). Replaces the previous one (empty:
  // none); once this returns, the previous one is not running and never runs again.
  virtual void on_owed_stops_changed(std::function<void()> changed) = 0;

  // Lends the bus's serial line to someone else (the console's commissioning, docs/CONSOLE.md):
  // at the next transaction boundary the engine closes the port and keeps the bus down — client
  // work is refused (BusDown, saying `why`), the port is not reopened, owed safe stops are kept —
  // until take_back_line(). Blocks until the port is closed; false when that took longer than
  // `bound` (the line may still be in use: do not open it). Not from the bus thread.
  virtual bool lend_line(std::string why, std::chrono::milliseconds bound) = 0;
  // Ends a lend: the port is opened again at once (owed stops first, then discovery, as after a
  // port loss). False (and nothing done) when no lend was asked for.
  virtual bool take_back_line() = 0;
  // True from the moment a lent line's port is closed until it is taken back.
  virtual bool line_lent() const = 0;

  virtual const BusSettings& settings() const = 0;
  virtual bool bus_up() const = 0;
  virtual BusCountersSnapshot counters() const = 0;
  virtual const PollCache& cache() const = 0;
  // True once discovery has finished for the current bus-up period (tests, readiness).
  virtual bool discovered() const = 0;
};

// The engine for the bus's protocol: EngineCore (engine_core.h) with PacketTransactor for feetech
// and d55d, with RtuTransactor (and the bus's RS-485/RTS/byte-timeout options) for modbus-rtu.
// Throws std::invalid_argument for settings it cannot run (a servo whose table is not spoken on
// the bus, an empty poll block, duplicate IDs).
std::unique_ptr<BusEngine> make_bus_engine(BusSettings settings, const config::ModbusRtuOptions& modbus_rtu = {});

}  // namespace sms::gateway
