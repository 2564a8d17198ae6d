#pragma once
// What an upstream Modbus RTU port counts (/metrics: docs/RTU_PANELS.md "Metrics"). Plain
// values, so the metrics code needs no more than this header. Every frame the port receives is
// counted once: requests, crc_errors, dropped_frames, echoes or silent_units.
#include <cstdint>
#include <string>

namespace sms::gateway {

struct RtuSlaveStats {
  std::string device;
  bool open = false;
  std::uint64_t requests = 0;        // valid frames for a unit the port serves, broadcasts included
  std::uint64_t answers = 0;         // answer frames sent
  std::uint64_t broadcasts = 0;      // broadcast writes carried out (never answered)
  std::uint64_t crc_errors = 0;      // frames whose CRC did not check
  std::uint64_t dropped_frames = 0;  // a t1.5 gap inside, shorter than 4 or longer than 256 bytes, a queue overrun
  std::uint64_t echoes = 0;          // the adapter's echo of an answer (identical, in time): not a request
  std::uint64_t silent_units = 0;    // valid frames for a unit the port does not serve: not answered
  std::uint64_t role_refusals = 0;   // requests the port's role may not make (answered 0x01 / 0x02)
  std::uint64_t port_lost = 0;       // times the device failed or vanished
};

}  // namespace sms::gateway
