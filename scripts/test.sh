#!/usr/bin/env bash
# The one command that runs every test: installs dependencies; checks the format of every C++
# file (scripts/format.sh --check, .clang-format); builds with clang and AddressSanitizer +
# UndefinedBehaviorSanitizer into build-asan/ and runs clang-tidy over the product's sources
# (scripts/tidy.sh, .clang-tidy; unchanged files that passed are not checked again), runs ctest; then builds the
# libFuzzer targets with clang into build-fuzz/ and runs each briefly (SMS_SKIP_FUZZ=1 skips them;
# scripts/fuzz.sh is the longer run); then a ThreadSanitizer build of the gateway's unit tests
# runs the threaded suites again (SMS_SKIP_TSAN=1 skips it).
# Why clang here: it compiles this code with the sanitizers about twice as fast as GCC 12 (the
# build was more than half of the command's time) and its -Wall finds other mistakes; GCC 12 builds
# the benchmarks (scripts/bench.sh) and the container image with the same -Werror flags
# (SMS_WERROR=ON; off by default, so the run command and packagers' builds never fail on a warning).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
# First the checks that take seconds: a file off the house format fails the run before the build.
./scripts/format.sh --check
jobs=$(nproc)
# A build-asan/ configured with another compiler is configured anew (CMake cannot switch in place).
if [ -f build-asan/CMakeCache.txt ] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*clang++' build-asan/CMakeCache.txt; then
  rm -rf build-asan
fi
cmake -S . -B build-asan -G Ninja -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DSMS_SANITIZE=ON -DSMS_WERROR=ON \
  -DSMS_BUILD_BENCH=OFF >/dev/null
cmake --build build-asan -j "$jobs"
./scripts/tidy.sh build-asan
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
ctest --test-dir build-asan --output-on-failure -j "$jobs" "$@"
# ThreadSanitizer: the ASan build cannot see data races. The suites where threads meet — bus
# engines, the safety supervisor, the TCP server, the unit router, MQTT — run again under TSan
# (build-tsan/, the gateway's unit tests only: processes spawned by e2e tests are not traced).
if [ "${SMS_SKIP_TSAN:-0}" != 1 ]; then
  if [ -f build-tsan/CMakeCache.txt ] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*clang++' build-tsan/CMakeCache.txt; then
    rm -rf build-tsan
  fi
  cmake -S . -B build-tsan -G Ninja -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DSMS_TSAN=ON -DSMS_WERROR=ON \
    -DSMS_BUILD_BENCH=OFF >/dev/null
  # Only the test programs that hold those suites (the console's, the monitor's and the RTU
  # slave's tests are not run here).
  cmake --build build-tsan -j "$jobs" --target gateway_bus_tests gateway_units_tests gateway_modbus_tcp_tests \
    gateway_observability_tests gateway_tools_tests
  TSAN_OPTIONS="halt_on_error=1 second_deadlock_stack=1" \
    ctest --test-dir build-tsan --output-on-failure -j "$jobs" \
    -R 'SafetyState|BusEngineTest|QueueTest|LateReplyTest|Conformance|Fairness|Scheduling|MotionGateTest|TcpServerTest|Router|RtuEngine|RtuContractTest|MetricsOfARunningGateway|BusReopen|BusLend|EchoTest|PollCycleTest|StatusByte' "$@"
fi
if [ "${SMS_SKIP_FUZZ:-0}" != 1 ]; then
  ./scripts/fuzz.sh --build
  ctest --test-dir build-fuzz --output-on-failure -j "$jobs" "$@"
fi
# ARM, light form (docs/ARM.md "In the test command"): the protocol and modbus_map suites cross-built
# for armhf (32-bit ARMv7: 32-bit long, size_t and time_t; unsigned char) and run under qemu-arm,
# on a machine where scripts/cross.sh finds its cross toolchain, qemu and the armhf sysroot ready
# (`scripts/cross.sh armhf --deps-only` makes them, a few minutes once); elsewhere it says so. The
# test command itself installs nothing for it. SMS_SKIP_ARM=1 skips it.
if [ "${SMS_SKIP_ARM:-0}" != 1 ]; then
  if arm_ready=$(./scripts/cross.sh armhf --ready 2>&1); then
    ./scripts/cross.sh armhf --test-light --suites protocol_tests,modbus_map_tests
  else
    echo "test.sh: ARM light step not run: ${arm_ready##*: } (scripts/cross.sh armhf --deps-only installs it)"
  fi
fi
