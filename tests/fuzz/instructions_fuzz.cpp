// libFuzzer target: the request parsers of protocol/instructions.h, feetech.h and d55d.h, which
// the simulator runs on the params of every packet it decodes. The whole input is one params
// field, handed to every parser.
//
// Invariants, for each parser:
//   - it accepts exactly the params its header comment calls well-formed (written out again
//     here from that comment, not derived from the parser);
//   - what it accepts, the matching builder turns back into the same params byte for byte
//     (or refuses with std::length_error when they exceed what LEN can carry).
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>

#include "fuzz_support.h"
#include "protocol/d55d.h"
#include "protocol/feetech.h"
#include "protocol/instructions.h"
#include "protocol/packet.h"

namespace {

namespace protocol = sms::protocol;
using sms::fuzz::hex;
using Params = std::span<const std::uint8_t>;

constexpr std::uint8_t kId = 1;

// Runs `build` and checks it reproduces `params`, or refuses params longer than LEN allows.
template <typename Build>
void check_rebuilds(const char* what, Params params, Build&& build) {
  try {
    const protocol::Packet packet = build();
    SMS_FUZZ_CHECK(std::equal(packet.params.begin(), packet.params.end(), params.begin(), params.end()),
                   std::string(what) + ": parsed " + hex(params) + ", rebuilt " + hex(packet.params));
  } catch (const std::length_error&) {
    SMS_FUZZ_CHECK(params.size() > protocol::kMaxParams,
                   std::string(what) + ": builder refused " + std::to_string(params.size()) + " bytes, LEN holds them");
  }
}

void check_common(Params params) {
  const bool read_ok = params.size() == 2 && params[1] != 0;
  const auto read = protocol::parse_read(params);
  SMS_FUZZ_CHECK(read.has_value() == read_ok, "parse_read acceptance wrong for " + hex(params));
  if (read) check_rebuilds("READ", params, [&] { return protocol::read(kId, read->address, read->count); });

  const bool write_ok = params.size() >= 2;
  const auto write = protocol::parse_write(params);
  SMS_FUZZ_CHECK(write.has_value() == write_ok, "parse_write acceptance wrong for " + hex(params));
  if (write) {
    check_rebuilds("WRITE", params, [&] { return protocol::write(kId, write->address, write->data); });
    check_rebuilds("REG WRITE", params, [&] { return protocol::reg_write(kId, write->address, write->data); });
  }

  const bool sync_write_ok = params.size() > 2 && params[1] != 0 && (params.size() - 2) % (params[1] + 1U) == 0;
  const auto sync_write = protocol::parse_sync_write(params);
  SMS_FUZZ_CHECK(sync_write.has_value() == sync_write_ok, "parse_sync_write acceptance wrong for " + hex(params));
  if (sync_write) {
    SMS_FUZZ_CHECK(sync_write->entries.size() == (params.size() - 2) / (params[1] + 1U),
                   "parse_sync_write entry count wrong for " + hex(params));
    check_rebuilds("SYNC WRITE", params,
                   [&] { return protocol::sync_write(sync_write->address, sync_write->length, sync_write->entries); });
  }
}

void check_feetech(Params params) {
  const bool sync_read_ok = params.size() >= 3 && params[1] != 0;
  const auto sync_read = protocol::feetech::parse_sync_read(params);
  SMS_FUZZ_CHECK(sync_read.has_value() == sync_read_ok, "parse_sync_read acceptance wrong for " + hex(params));
  if (sync_read) {
    check_rebuilds("SYNC READ", params,
                   [&] { return protocol::feetech::sync_read(sync_read->address, sync_read->count, sync_read->ids); });
  }

  const auto calibrate = protocol::feetech::parse_calibrate(params);
  SMS_FUZZ_CHECK(calibrate.has_value() == (params.empty() || params.size() == 2),
                 "parse_calibrate acceptance wrong for " + hex(params));
  if (calibrate) {
    SMS_FUZZ_CHECK(calibrate->has_value() == !params.empty(), "parse_calibrate position presence wrong");
    check_rebuilds("CALIBRATE", params, [&] { return protocol::feetech::calibrate(kId, *calibrate); });
  }
}

void check_d55d(Params params) {
  const bool trajectory_ok = !params.empty() && params[0] != 0 && params.size() == 1 + 3 * std::size_t{params[0]};
  const auto trajectory = protocol::d55d::parse_trajectory_write(params);
  SMS_FUZZ_CHECK(trajectory.has_value() == trajectory_ok, "parse_trajectory_write acceptance wrong for " + hex(params));
  if (trajectory) {
    check_rebuilds("TRAJECTORY WRITE", params, [&] { return protocol::d55d::trajectory_write(kId, *trajectory); });
  }

  // docs/PROTOCOL.md §1.2: sub 0x01 takes 4 or 6 bytes, 0x02 takes 6, 0x03 takes 2.
  bool custom_ok = false;
  if (!params.empty()) {
    const std::size_t body = params.size() - 1;
    custom_ok = (params[0] == 0x01 && (body == 4 || body == 6)) || (params[0] == 0x02 && body == 6) ||
                (params[0] == 0x03 && body == 2);
  }
  const auto custom = protocol::d55d::parse_custom(params);
  SMS_FUZZ_CHECK(custom.has_value() == custom_ok, "parse_custom acceptance wrong for " + hex(params));
  if (custom) check_rebuilds("CUSTOM", params, [&] { return protocol::d55d::custom(kId, *custom); });
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const Params params(data, size);
  check_common(params);
  check_feetech(params);
  check_d55d(params);
  return 0;
}
