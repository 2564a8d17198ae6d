#pragma once
// Shared pieces of the libFuzzer targets: an invariant check that stops the run with a
// readable message (libFuzzer then saves the input), and the "chunked stream" input layout
// the decoder targets use so that the fuzzer controls where reads split the byte stream.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <span>
#include <string>

namespace sms::fuzz {

// A broken invariant is a finding: print what and where, then abort so libFuzzer keeps the input.
[[noreturn]] inline void invariant_failed(const char* condition, const char* file, int line, const std::string& what) {
  std::fprintf(stderr, "\n%s:%d: invariant broken: %s\n  %s\n", file, line, condition, what.c_str());
  std::abort();
}

#define SMS_FUZZ_CHECK(condition, what)                                                      \
  do {                                                                                       \
    if (!(condition)) ::sms::fuzz::invariant_failed(#condition, __FILE__, __LINE__, (what)); \
  } while (false)

inline std::string hex(std::span<const std::uint8_t> bytes) {
  static constexpr char kDigits[] = "0123456789ABCDEF";
  std::string out;
  out.reserve(bytes.size() * 3);
  for (const std::uint8_t byte : bytes) {
    if (!out.empty()) out += ' ';
    out += kDigits[byte >> 4];
    out += kDigits[byte & 0x0F];
  }
  return out;
}

// Input layout of the decoder targets, chosen so a seed file is readable in a hex dump:
//   K | OP_1 .. OP_K | STREAM
// K (mod 16) op bytes are applied in a cycle until STREAM is used up. An op feeds the next
// OP bytes of STREAM (0 feeds an empty span: a read that returned nothing), except
// kBoundaryOp, which asks the target for its "boundary" action between feeds (reset(), or
// the 3.5-character silence for Modbus RTU). K = 0 feeds STREAM in one piece.
inline constexpr std::uint8_t kBoundaryOp = 0xFF;
inline constexpr std::size_t kMaxOps = 16;

struct ChunkedInput {
  std::span<const std::uint8_t> ops;
  std::span<const std::uint8_t> stream;
};

inline ChunkedInput split_chunked_input(std::span<const std::uint8_t> data) {
  if (data.empty()) return {};
  const std::size_t op_count = std::min<std::size_t>(data[0] % kMaxOps, data.size() - 1);
  return {data.subspan(1, op_count), data.subspan(1 + op_count)};
}

// Calls feed(chunk) and boundary() as the ops say, in stream order. A cycle of ops that only
// holds boundaries and empty feeds would never finish: after one such cycle the rest is fed whole.
template <typename Feed, typename Boundary>
void play_chunked(const ChunkedInput& input, Feed&& feed, Boundary&& boundary) {
  std::span<const std::uint8_t> rest = input.stream;
  if (input.ops.empty()) {
    feed(rest);
    return;
  }
  while (!rest.empty()) {
    const std::size_t before = rest.size();
    for (const std::uint8_t op : input.ops) {
      if (op == kBoundaryOp) {
        boundary();
        continue;
      }
      const std::size_t size = std::min<std::size_t>(op, rest.size());
      feed(rest.first(size));
      rest = rest.subspan(size);
    }
    if (rest.size() == before) {
      feed(rest);
      rest = {};
    }
  }
}

}  // namespace sms::fuzz
