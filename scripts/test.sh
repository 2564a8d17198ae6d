#!/usr/bin/env bash
# The one command that runs every test (README "The two commands" says how long it takes). In
# order:
#   1. installs dependencies (scripts/install-deps.sh) and checks the format of every C++ file
#      (scripts/format.sh --check, .clang-format);
#   2. builds every target of the default build (product, tests, benchmarks) with clang and
#      AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/, and runs clang-tidy over
#      the product's sources (scripts/tidy.sh; unchanged files that passed are not checked again);
#   3. builds the same targets with GCC 12 into build-gcc/ (the compiler of packagers, of
#      scripts/bench.sh and of the container image), in the background at the lowest priority
#      while ctest runs;
#   4. runs ctest: every suite, and each benchmark once in its shortest form
#      (bench/programs.txt), so a benchmark that no longer builds or runs fails here;
#   5. a ThreadSanitizer build of the gateway's threaded suites (SMS_SKIP_TSAN=1 skips it);
#   6. the libFuzzer targets, briefly (SMS_SKIP_FUZZ=1 skips them; scripts/fuzz.sh runs longer);
#   7. the ARM light step where its cross toolchain is installed (docs/ARM.md; SMS_SKIP_ARM=1);
#   8. the container image built from HEAD and checked (scripts/container-test.sh --head) where
#      podman is installed (SMS_SKIP_CONTAINER=1 skips it).
# Arguments are passed to each ctest run (e.g. -R Safety).
# Why clang for the sanitizer build: it compiles this code with the sanitizers about twice as fast
# as GCC 12, and its -Wall finds other mistakes; GCC's build in step 3 needs no sanitizers.
# Warnings are errors in every build here (SMS_WERROR=ON; off by default, so the run command and
# packagers' builds never fail on a warning).
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
# ccache where it is installed (scripts/install-deps.sh installs it): a second run recompiles only
# what changed. Paths inside the checkout are hashed relative to it, so another clone (CI's) hits
# the same entries.
launcher=()
command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
export CCACHE_BASEDIR=${CCACHE_BASEDIR:-$PWD}
cmake -S . -B build-asan -G Ninja -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DSMS_SANITIZE=ON -DSMS_WERROR=ON \
  -DSMS_BUILD_BENCH=ON "${launcher[@]}" >/dev/null
cmake --build build-asan -j "$jobs"
./scripts/tidy.sh build-asan

# GCC 12, every default target, the default build type (RelWithDebInfo, -O2, as a plain
# `cmake -S . -B build` makes it), beside ctest at the lowest priority: the suites must pass on a
# loaded machine anyway, and the cores ctest leaves idle while tests wait on the simulator do the
# work. Its log is shown only when it fails.
if [ -f build-gcc/CMakeCache.txt ] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*g++' build-gcc/CMakeCache.txt; then
  rm -rf build-gcc
fi
cmake -S . -B build-gcc -G Ninja -DCMAKE_CXX_COMPILER=g++ -DSMS_WERROR=ON "${launcher[@]}" >/dev/null
nice -n 19 cmake --build build-gcc -j "$jobs" >build-gcc/build.log 2>&1 &
gcc_build=$!

export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
ctest_status=0
ctest --test-dir build-asan --output-on-failure -j "$jobs" "$@" || ctest_status=$?
if ! wait "$gcc_build"; then
  grep -B2 -A20 -m3 -E 'error|FAILED' build-gcc/build.log >&2 || tail -40 build-gcc/build.log >&2
  echo "test.sh: the GCC 12 build failed (build-gcc/build.log)" >&2
  exit 1
fi
echo "test.sh: GCC 12 built every default target (build-gcc/)"
[ "$ctest_status" -eq 0 ] || exit "$ctest_status"
# ThreadSanitizer: the ASan build cannot see data races. The suites where threads meet — bus
# engines, the safety supervisor, the TCP server, the unit router, MQTT — run again under TSan
# (build-tsan/, the gateway's unit tests only: processes spawned by e2e tests are not traced).
if [ "${SMS_SKIP_TSAN:-0}" != 1 ]; then
  if [ -f build-tsan/CMakeCache.txt ] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*clang++' build-tsan/CMakeCache.txt; then
    rm -rf build-tsan
  fi
  cmake -S . -B build-tsan -G Ninja -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DSMS_TSAN=ON -DSMS_WERROR=ON \
    -DSMS_BUILD_BENCH=OFF "${launcher[@]}" >/dev/null
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
# on a machine where scripts/cross.sh finds its cross toolchain, qemu and the armhf sysroot ready.
# The test command does not install them: `scripts/cross.sh armhf --deps-only` takes several
# minutes and a few hundred MB, which a fresh CI machine would pay on every run (README "The two commands").
if [ "${SMS_SKIP_ARM:-0}" != 1 ]; then
  if arm_ready=$(./scripts/cross.sh armhf --ready 2>&1); then
    ./scripts/cross.sh armhf --test-light --suites protocol_tests,modbus_map_tests
  else
    echo "test.sh: ARM light step not run: ${arm_ready##*: } (scripts/cross.sh armhf --deps-only installs it)"
  fi
fi
# The container image from the committed HEAD, built and run as the README says, where podman is
# installed (it needs root; it installs runc, podman's runtime here).
if [ "${SMS_SKIP_CONTAINER:-0}" != 1 ]; then
  if command -v podman >/dev/null && [ "$(id -u)" -eq 0 ]; then
    ./scripts/container-test.sh --head
  else
    echo "test.sh: container check not run: needs podman and root (apt-get install podman buildah debootstrap; scripts/container-test.sh)"
  fi
fi
