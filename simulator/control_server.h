#pragma once
// The control socket of `sms-sim --control PATH`: a unix stream socket speaking one command
// per line, one reply line per command, so out-of-process tests and scripts inject faults
// while the bus runs:
//
//   offline 3 | online 3          take servo 3 off the bus / back
//   drop 0.5 | corrupt 0.1        reply drop / corruption probability
//   corrupt-next [N]              corrupt the next N replies (default 1)
//   late 2 50                     servo 2 answers 50 ms late (0 = on time)
//   error 2 0x04                  servo 2 reports these ERROR/status bits (0 clears)
//   duplicate 4                   a second servo with ID 4 answers too
//   timing on|off                 wire timing
//   get 3 56 2                    -> "18 05" (hex bytes; SMSMB: registers, 2 bytes each)
//   set 3 42 00 08                write hex bytes from address 42 (test backdoor, any field)
//   field 3 present_position      -> the field's value, decimal, signed where the field is
//   motion 3                      -> "started_us=.. arrived_us=.. position=.. goal=.. at_goal_write=..
//                                    read_before_goal=.. reversed=0|1 turned_back=N heartbeat_stops=N"
//                                    (steady-clock µs of the last goal written in position mode and of its
//                                    arrival, "-": none; where the motor was when that goal was written, and
//                                    when it answered the last read before it; whether it turned back since its last
//                                    command, and how far from the farthest point it reached; how often its
//                                    d55d heartbeat stopped it)
//   holds                         -> "ENDED_US:HELD_US ..." or "none": the last times (at most 256) the
//                                    machine held the bus thread 5 ms or more past its wake-up (steady
//                                    clock µs of the hold's end, its length): no request was read meanwhile
//   list                          -> "1:sts:feetech:1000000 2:..." (current ID and baud)
//   stats                         -> "requests=.. replies=.. dropped=.. corrupted=.. collisions=.. checksum_errors=.."
//   help
// Replies: "ok", the data asked for, or "error: <what>". Numbers are decimal or 0x hex; the
// bytes of `set` are hex.
#include <memory>
#include <string>
#include <string_view>

#include "simulator/simulated_bus.h"

namespace sms::simulator {

// Runs one command line against `bus`; returns the reply line (no newline).
std::string execute_control_command(SimulatedBus& bus, std::string_view line);

class ControlServer {
 public:
  // Binds and listens (an existing socket file at `path` is replaced). Throws std::system_error.
  ControlServer(SimulatedBus& bus, std::string path);
  ~ControlServer();  // stops the thread, removes the socket file
  ControlServer(const ControlServer&) = delete;
  ControlServer& operator=(const ControlServer&) = delete;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sms::simulator
