#!/usr/bin/env bash
# The one command that runs every test (README "The two commands" says how long it takes). In
# order:
#   1. installs dependencies (scripts/install-deps.sh) and checks the format of every C++ file
#      (scripts/format.sh --check, .clang-format);
#   2. builds every target of the default build (product, tests, benchmarks) with clang and
#      AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/;
#   3. runs ctest: every suite, and each benchmark once in its shortest form
#      (bench/programs.txt), so a benchmark that no longer builds or runs fails here;
#      beside it, at the lowest priority, the checks that need no test: clang-tidy over the
#      product's sources (scripts/tidy.sh), GCC 12's front end over every file of the default
#      build (scripts/gcc-check.sh: the compiler of packagers, scripts/bench.sh and the container
#      image), then the ThreadSanitizer and fuzzer builds; a check that passed on an unchanged
#      file is not run again (scripts/check_once.py);
#   4. the gateway's threaded suites again under ThreadSanitizer (SMS_SKIP_TSAN=1 skips it);
#   5. the libFuzzer targets, briefly (SMS_SKIP_FUZZ=1 skips them; scripts/fuzz.sh runs longer);
#   6. the ARM light step where its cross toolchain is installed (docs/ARM.md; SMS_SKIP_ARM=1);
#   7. the container image built from HEAD and checked (scripts/container-test.sh --head) where
#      podman is installed (SMS_SKIP_CONTAINER=1 skips it).
# At the end it prints how long each step took. Arguments are passed to each ctest run (e.g. -R Safety).
# Why clang for the sanitizer build: it compiles this code with the sanitizers about twice as fast
# as GCC 12, and its -Wall finds other mistakes. Why GCC's front end and not a GCC build: a
# GCC -O2 build costs 5 times the CPU of the front end alone, and on 2 cores that was most of the
# command's time (docs/DECISIONS.md "GCC in the test command").
# Warnings are errors in every build here (SMS_WERROR=ON; off by default, so the run command and
# packagers' builds never fail on a warning).
set -euo pipefail
cd "$(dirname "$0")/.."
began=$SECONDS
steps=()
# record NAME SECONDS / took NAME SINCE: how long a step took, for the summary at the end.
record() { steps+=("$(printf '%-36s %4d s' "$1" "$2")"); }
took() { record "$1" $((SECONDS - $2)); }
summary() {
  echo "test.sh: how long each step took (the checks ran beside ctest, at the lowest priority):"
  [ "${#steps[@]}" -eq 0 ] || printf '  %s\n' "${steps[@]}"
  echo "test.sh: $((SECONDS - began)) s in all"
}
trap summary EXIT

step=$SECONDS
./scripts/install-deps.sh
# First the checks that take seconds: a file off the house format fails the run before the build.
./scripts/format.sh --check
took "dependencies and format" "$step"
jobs=$(nproc)
# A build dir configured with another compiler is configured anew (CMake cannot switch in place).
# The compiler's name is compared whole: "g++" is also the end of "clang++".
fresh_with() {
  local cached
  [ -f "$1/CMakeCache.txt" ] || return 0
  cached=$(sed -n 's/^CMAKE_CXX_COMPILER:[A-Z]*=//p' "$1/CMakeCache.txt")
  [ "$(basename "$cached")" = "$2" ] || rm -rf "$1"
}
# ccache where it is installed (scripts/install-deps.sh installs it): a second run recompiles only
# what changed. Paths inside the checkout are hashed relative to it, and the working directory
# not at all (ccache hashes it where a compile makes debug info, unless told not to), so another
# clone (CI's) hits the same entries.
launcher=()
command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
export CCACHE_BASEDIR=${CCACHE_BASEDIR:-$PWD} CCACHE_NOHASHDIR=${CCACHE_NOHASHDIR:-1}
# The sanitizer builds' compile and link (docs/DECISIONS.md "The test command is the whole truth"):
# line tables only, which is what a sanitizer report needs for file:line in every frame (full
# debug info is for a debugger and costs a quarter of clang's compile time here); lld where it is
# installed (scripts/install-deps.sh installs it), a quarter of ld.bfd's link time.
sanitizer_build=(-DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS_DEBUG=-gline-tables-only)
if command -v ld.lld >/dev/null; then
  sanitizer_build+=(-DCMAKE_EXE_LINKER_FLAGS=-fuse-ld=lld -DCMAKE_SHARED_LINKER_FLAGS=-fuse-ld=lld)
fi
step=$SECONDS
fresh_with build-asan 'clang++'
cmake -S . -B build-asan -G Ninja "${sanitizer_build[@]}" -DSMS_SANITIZE=ON -DSMS_WERROR=ON \
  -DSMS_BUILD_BENCH=ON "${launcher[@]}" >/dev/null
cmake --build build-asan -j "$jobs"
took "clang ASan+UBSan build" "$step"

# The checks beside ctest, one after another at the lowest priority: the suites must pass on a
# loaded machine anyway, and the cores ctest leaves idle while tests wait on the simulator do the
# work. Each one's log is shown only when it fails.
fresh_with build-gcc 'g++'
cmake -S . -B build-gcc -G Ninja -DCMAKE_CXX_COMPILER=g++ -DSMS_WERROR=ON >/dev/null  # configured only: its compile database
run_tsan=0
[ "${SMS_SKIP_TSAN:-0}" != 1 ] && run_tsan=1
run_fuzz=0
[ "${SMS_SKIP_FUZZ:-0}" != 1 ] && run_fuzz=1
checks=build-asan/checks
rm -rf "$checks"
mkdir -p "$checks"
beside() {
  local name=$1 start=$SECONDS
  shift
  if "$@" >"$checks/$name.log" 2>&1; then
    echo "$name $((SECONDS - start))" >>"$checks/passed"
  else
    echo "$name $((SECONDS - start))" >>"$checks/failed"
  fi
}
tsan_build() {
  # ThreadSanitizer: the ASan build cannot see data races. The suites where threads meet run again
  # under TSan (build-tsan/, the gateway's unit tests only: processes spawned by e2e tests are
  # not traced); only the test programs that hold those suites are built.
  fresh_with build-tsan 'clang++'
  cmake -S . -B build-tsan -G Ninja "${sanitizer_build[@]}" -DSMS_TSAN=ON -DSMS_WERROR=ON \
    -DSMS_BUILD_BENCH=OFF "${launcher[@]}" >/dev/null
  cmake --build build-tsan -j "$jobs" --target gateway_bus_tests gateway_units_tests gateway_modbus_tcp_tests \
    gateway_observability_tests gateway_tools_tests
}
(
  renice -n 19 -p "$BASHPID" >/dev/null  # before anything starts: what it starts inherits it
  beside clang-tidy ./scripts/tidy.sh build-asan
  beside gcc-front-end ./scripts/gcc-check.sh build-gcc
  [ "$run_tsan" = 0 ] || beside tsan-build tsan_build
  [ "$run_fuzz" = 0 ] || beside fuzz-build ./scripts/fuzz.sh --build
) </dev/null &
beside_pid=$!
# Stops the checks, with everything they started, if the command ends before they do.
kill_tree() {
  local child
  for child in $(pgrep -P "$1"); do kill_tree "$child"; done
  kill "$1" 2>/dev/null || true
}
trap 'kill_tree "$beside_pid"; summary' EXIT

export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
step=$SECONDS
ctest_status=0
ctest --test-dir build-asan --output-on-failure -j "$jobs" "$@" || ctest_status=$?
took "ctest (build-asan)" "$step"
step=$SECONDS
wait "$beside_pid" || true
trap summary EXIT
took "the checks beside it, after ctest" "$step"
for outcome in passed failed; do
  [ -f "$checks/$outcome" ] || continue
  while read -r name seconds; do record "  $name ($outcome)" "$seconds"; done <"$checks/$outcome"
done
if [ -f "$checks/failed" ]; then
  while read -r name _; do
    echo "test.sh: $name failed ($checks/$name.log):" >&2
    grep -B2 -A20 -m5 -E 'error|warning|FAILED|findings' "$checks/$name.log" >&2 || tail -40 "$checks/$name.log" >&2
  done <"$checks/failed"
  exit 1
fi
[ "$ctest_status" -eq 0 ] || exit "$ctest_status"
if [ "$run_tsan" = 1 ]; then
  step=$SECONDS
  TSAN_OPTIONS="halt_on_error=1 second_deadlock_stack=1" \
    ctest --test-dir build-tsan --output-on-failure -j "$jobs" \
    -R 'SafetyState|BusEngineTest|QueueTest|LateReplyTest|Conformance|Fairness|Scheduling|MotionGateTest|TcpServerTest|Router|RtuEngine|RtuContractTest|MetricsOfARunningGateway|BusReopen|BusLend|EchoTest|PollCycleTest|StatusByte' "$@"
  took "ctest (build-tsan)" "$step"
fi
if [ "$run_fuzz" = 1 ]; then
  step=$SECONDS
  ctest --test-dir build-fuzz --output-on-failure -j "$jobs" "$@"
  took "fuzzers" "$step"
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
