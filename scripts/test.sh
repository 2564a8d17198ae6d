#!/usr/bin/env bash
# The one command that runs every test (tests/README.md "How long it takes" says how long). In
# order:
#   1. installs dependencies (scripts/install-deps.sh) and checks the format of every C++ file
#      (scripts/format.sh --check, .clang-format);
#   2. builds every target of the default build (product, tests, benchmarks) with clang and
#      AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/;
#   3. runs ctest there: every suite, and each benchmark once in its shortest form
#      (bench/programs.txt), so a benchmark that no longer builds or runs fails here; more tests
#      at once than cores (SMS_TEST_JOBS, default 3 a core): they mostly wait on the simulator.
#      Beside it, in three lanes of their own:
#      - the checks: clang-tidy over the product's sources (scripts/tidy.sh) and GCC 12's front end
#        over every file of the default build (scripts/gcc-check.sh: the compiler of packagers,
#        scripts/bench.sh and the container image), each over the files the change touched and
#        those including a touched header, against the commit it builds on, the full sweep where
#        that is unknown (as on CI) (scripts/check_once.py, which also skips a file that passed
#        unchanged);
#      - the other sanitizers: the ThreadSanitizer build and the gateway's threaded suites under
#        it (SMS_SKIP_TSAN=1 skips them); then the libFuzzer targets, built and run briefly, each
#        whose program or seed corpus changed since it last passed here (SMS_SKIP_FUZZ=1;
#        scripts/fuzz.sh runs longer); the builds beside ctest, the suites once it has ended;
#      - the container image built from HEAD and checked (scripts/container-test.sh --head) once
#        ctest has ended, where podman is installed (SMS_SKIP_CONTAINER=1 skips it).
#      Builds and checks there run at the lowest priority; suites at normal priority.
#   4. the ARM light step where its cross toolchain is installed (docs/ARM.md; SMS_SKIP_ARM=1).
# It fails fast: the first failure anywhere ends the command at once, with the failing test's
# output (the tests still running beside it are stopped and named) or the failing item's log; the
# lanes are stopped by their process ids. At the end, failed or not, it prints how long each step
# took. Arguments are passed to each ctest run (e.g. -R Safety).
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
  echo "test.sh: how long each step took (indented: the lanes beside ctest, each item from its start):"
  [ "${#steps[@]}" -eq 0 ] || printf '  %s\n' "${steps[@]}"
  echo "test.sh: $((SECONDS - began)) s in all"
}
trap summary EXIT

step=$SECONDS
./scripts/install-deps.sh
# First the checks that take seconds: a file off the house format fails the run before the build.
./scripts/format.sh --check || { took "dependencies and format FAILED" "$step"; exit 1; }
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
# Unity build (CMAKE_UNITY_BUILD): each target's sources compile in batches of 8, which parse
# Asio, Beast, spdlog and gtest once a batch instead of once a file: 45 % less CPU for a cold
# build (tests/README.md "How long it takes"); a changed file recompiles its batch. The compile
# database then lists the batches; scripts/check_once.py reads them as the files they hold.
sanitizer_build=(-DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS_DEBUG=-gline-tables-only
  -DCMAKE_UNITY_BUILD=ON)
if command -v ld.lld >/dev/null; then
  sanitizer_build+=(-DCMAKE_EXE_LINKER_FLAGS=-fuse-ld=lld -DCMAKE_SHARED_LINKER_FLAGS=-fuse-ld=lld)
fi
step=$SECONDS
fresh_with build-asan 'clang++'
cmake -S . -B build-asan -G Ninja "${sanitizer_build[@]}" -DSMS_SANITIZE=ON -DSMS_WERROR=ON \
  -DSMS_BUILD_BENCH=ON "${launcher[@]}" >/dev/null
cmake --build build-asan -j "$jobs" || { took "clang ASan+UBSan build FAILED" "$step"; exit 1; }
took "clang ASan+UBSan build" "$step"

# Beside ctest, in three lanes of their own: the checks (clang-tidy, GCC's front end), the other
# sanitizers (the ThreadSanitizer build and its suites, then the fuzzer build and the fuzzers), and
# the container image (built, then run and checked). Builds and checks run at the lowest priority, on the cores
# the suites leave idle while they wait on the simulator; the suites (ThreadSanitizer's, the
# fuzzers, the image's checks) at normal priority: they must pass on a loaded machine anyway.
# Each item's log is shown only when it fails.
fresh_with build-gcc 'g++'
cmake -S . -B build-gcc -G Ninja -DCMAKE_CXX_COMPILER=g++ -DSMS_WERROR=ON >/dev/null  # configured only: its compile database
run_tsan=0
[ "${SMS_SKIP_TSAN:-0}" != 1 ] && run_tsan=1
run_fuzz=0
[ "${SMS_SKIP_FUZZ:-0}" != 1 ] && run_fuzz=1
run_container=0
if [ "${SMS_SKIP_CONTAINER:-0}" != 1 ]; then
  if command -v podman >/dev/null && [ "$(id -u)" -eq 0 ]; then
    run_container=1
  else
    echo "test.sh: container check not run: needs podman and root (apt-get install podman buildah debootstrap; scripts/container-test.sh)"
  fi
fi
# How many tests ctest runs at once: most of a test's time is spent waiting on the simulator, so
# more than the cores (docs/DECISIONS.md "The test command is the whole truth");
# scripts/test-under-load.sh runs as many.
test_jobs=${SMS_TEST_JOBS:-$((3 * jobs))}
checks=build-asan/checks
rm -rf "$checks"
mkdir -p "$checks"
# beside NAME COMMAND...: one item of a lane, its log kept; the first that fails ends its lane
# (and the command: below).
beside() {
  local name=$1 start=$SECONDS
  shift
  if "$@" >"$checks/$name.log" 2>&1; then
    echo "$name $((SECONDS - start))" >>"$checks/passed"
  else
    echo "$name $((SECONDS - start))" >>"$checks/failed"
    return 1
  fi
}
low() { nice -n 19 "$@"; }
# after_ctest: a lane's suites (ThreadSanitizer's, the fuzzers) and the image (its build writes
# hundreds of MB of layers; then its checks) wait for ctest to end. Beside ctest's first minutes (its longest tests go first: Chromium, the benchmarks,
# 60-servo buses) they held the simulators 0.2-5 s, past the response timeouts of the tests
# beside them (docs/DECISIONS.md "Lanes beside ctest"); the builds before them run beside ctest
# at the lowest priority.
after_ctest() { while [ ! -e "$checks/ctest-ended" ]; do sleep 1; done; }
tsan_build() {
  # ThreadSanitizer: the ASan build cannot see data races. The suites where threads meet run again
  # under TSan (build-tsan/, the gateway's unit tests only: processes spawned by e2e tests are
  # not traced); only the test programs that hold those suites are built.
  fresh_with build-tsan 'clang++'
  cmake -S . -B build-tsan -G Ninja "${sanitizer_build[@]}" -DSMS_TSAN=ON -DSMS_WERROR=ON \
    -DSMS_BUILD_BENCH=OFF "${launcher[@]}" >/dev/null
  low cmake --build build-tsan -j "$jobs" --target gateway_bus_tests gateway_units_tests gateway_modbus_tcp_tests \
    gateway_observability_tests gateway_tools_tests
}
# fuzzers_to_run: the fuzz targets whose program or seed corpus differ from those of their last
# pass (build-fuzz/passed/NAME holds that fingerprint); fuzzers_passed NAME...: remember them.
fuzz_fingerprint() {
  { sha256sum "build-fuzz/bin/$1"; find "tests/fuzz/corpus/$1" -type f -print0 | sort -z | xargs -0r sha256sum; } |
    sha256sum | cut -d' ' -f1
}
fuzzers_to_run() {
  local binary name
  for binary in build-fuzz/bin/fuzz_*; do
    name=$(basename "$binary")
    [ "$(cat "build-fuzz/passed/$name" 2>/dev/null)" = "$(fuzz_fingerprint "$name")" ] || echo "$name"
  done
}
fuzzers_passed() {
  local name
  mkdir -p build-fuzz/passed
  for name in "$@"; do fuzz_fingerprint "$name" >"build-fuzz/passed/$name"; done
}
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
# The checks look at what changed since the last commit whose checks passed here (an ancestor of
# HEAD, kept in build-gcc/checks-passed-at), else at what check_once.py takes for the base (main's
# merge-base, or HEAD's parent): commits made while the command failed elsewhere are checked too.
checks_passed_at=build-gcc/checks-passed-at
if [ -z "${SMS_CHECK_BASE:-}" ] && [ -s "$checks_passed_at" ] &&
  git merge-base --is-ancestor "$(cat "$checks_passed_at")" HEAD 2>/dev/null; then
  SMS_CHECK_BASE=$(cat "$checks_passed_at")
  export SMS_CHECK_BASE
fi
checked_commit=$(git rev-parse HEAD 2>/dev/null || true)
(
  beside clang-tidy low ./scripts/tidy.sh build-asan || exit 1
  beside gcc-front-end low ./scripts/gcc-check.sh build-gcc || exit 1
  [ -n "$checked_commit" ] && echo "$checked_commit" >"$checks_passed_at"
  true
) </dev/null &
checks_pid=$!
(
  if [ "$run_tsan" = 1 ]; then
    beside tsan-build tsan_build || exit 1
    after_ctest
    TSAN_OPTIONS="halt_on_error=1 second_deadlock_stack=1" beside tsan-suites \
      ctest --test-dir build-tsan --output-on-failure --stop-on-failure -j "$jobs" \
      -R 'SafetyState|BusEngineTest|QueueTest|LateReplyTest|Conformance|Fairness|Scheduling|MotionGateTest|TcpServerTest|Router|RtuEngine|RtuContractTest|MetricsOfARunningGateway|BusReopen|BusLend|EchoTest|PollCycleTest|StatusByte' "$@" || exit 1
  fi
  if [ "$run_fuzz" = 1 ]; then
    beside fuzz-build low ./scripts/fuzz.sh --build || exit 1
    # As many at once as cores: each keeps a core busy for its whole run. A fuzzer whose program and seed
    # corpus are those of its last pass here is not run again (the run would only fuzz longer,
    # which scripts/fuzz.sh is for; a fresh clone runs them all).
    mapfile -t fuzzers < <(fuzzers_to_run)
    if [ "${#fuzzers[@]}" -gt 0 ]; then
      after_ctest
      beside fuzzers ctest --test-dir build-fuzz --output-on-failure --stop-on-failure -j "$jobs" \
        -R "^($(IFS='|'; echo "${fuzzers[*]}"))\$" "$@" || exit 1
      fuzzers_passed "${fuzzers[@]}"
    else
      echo "fuzzers-all-unchanged 0" >>"$checks/passed"
    fi
  fi
) </dev/null &
sanitizers_pid=$!
container_pid=
if [ "$run_container" = 1 ]; then
  # The image from the committed HEAD, built as the README says and run (it needs root; it installs
  # runc, podman's runtime here). Its build is most of the step: at the lowest priority first.
  (
    after_ctest
    beside image-build low ./scripts/container-test.sh --head --build-only || exit 1
    beside container ./scripts/container-test.sh --head || exit 1
  ) </dev/null &
  container_pid=$!
fi

# Fail fast: ctest and the lanes beside it run side by side, and whichever fails first ends the
# command at once, stopping the others by their process ids with everything they started.
# stop_tree PID: the process and all its descendants. They are frozen first, so that none starts
# another while the tree is walked, then terminated.
tree_of() {
  local child
  echo "$1"
  for child in $(pgrep -P "$1"); do tree_of "$child"; done
}
stop_tree() {
  local pids
  [ -n "$1" ] || return 0
  mapfile -t pids < <(tree_of "$1")
  kill -STOP "${pids[@]}" 2>/dev/null || true
  mapfile -t pids < <(tree_of "$1")
  kill -TERM "${pids[@]}" 2>/dev/null || true
  kill -CONT "${pids[@]}" 2>/dev/null || true
}
# The lanes' times, for the summary, and the log of the item that failed: from a failed suite's
# first failure, else the check's findings.
record_checks() {
  local outcome name seconds
  for outcome in passed failed; do
    [ -f "$checks/$outcome" ] || continue
    while read -r name seconds; do record "  $name ($outcome)" "$seconds"; done <"$checks/$outcome"
  done
  [ -f "$checks/failed" ] || return 0
  while read -r name _; do
    echo "test.sh: $name failed ($checks/$name.log):" >&2
    if grep -qP '\*\*\*(Failed|Timeout|Exception|Not Run(?! \(Disabled\)))' "$checks/$name.log"; then
      sed -n '/\*\*\*\(Failed\|Timeout\|Exception\|Not Run\)/,$p' "$checks/$name.log" | head -80 >&2
    else
      grep -B2 -A20 -m5 -E 'error|warning|FAILED|findings' "$checks/$name.log" >&2 || tail -40 "$checks/$name.log" >&2
    fi
  done < <(sed 's/ [0-9]*$//' "$checks/failed")
}

# ctest_fail_fast CTEST_ARGS...: ctest, its output shown as it runs, ended at the first failed
# test: that test's output is shown (--output-on-failure), then the tests still running are
# stopped and named (--stop-on-failure alone starts no new test but waits for them, the longest
# for a minute). Its status is ctest's, 8 for a failed test.
ctest_fail_fast() {
  local log=$checks/ctest-$BASHPID.log ctest_run tail_run status=0
  : >"$log"
  ctest --output-on-failure --stop-on-failure "$@" >"$log" 2>&1 &
  ctest_run=$!
  tail -n +1 -s 0.2 -f --pid="$ctest_run" "$log" &
  tail_run=$!
  while kill -0 "$ctest_run" 2>/dev/null; do
    # A failed, timed-out, crashed or missing test; a disabled one is no failure.
    if grep -qP '\*\*\*(Failed|Timeout|Exception|Not Run(?! \(Disabled\)))' "$log"; then
      sleep 1  # ctest writes the failed test's output right after its line
      stop_tree "$ctest_run"
      wait "$tail_run" || true
      echo "test.sh: a test failed; stopped the tests still running: $(awk '
        / Start +[0-9]+: / { number = $2; sub(":", "", number); name[number] = $3 }
        / Test +#[0-9]+: / { match($0, /#[0-9]+/); finished[substr($0, RSTART + 1, RLENGTH - 1)] = 1 }
        END { for (number in name) if (!(number in finished)) printf "%s ", name[number] }' "$log")" >&2
      return 8
    fi
    sleep 1
  done
  wait "$ctest_run" || status=$?
  wait "$tail_run" || true
  return "$status"
}

step=$SECONDS
ctest_fail_fast --test-dir build-asan -j "$test_jobs" "$@" &
ctest_pid=$!
trap 'stop_tree "$ctest_pid"; stop_tree "$checks_pid"; stop_tree "$sanitizers_pid"; stop_tree "$container_pid"; summary' EXIT
# stop_lanes: every lane still running, stopped with what it started.
stop_lanes() {
  stop_tree "$ctest_pid"
  stop_tree "$checks_pid"
  stop_tree "$sanitizers_pid"
  stop_tree "$container_pid"
  ctest_pid='' checks_pid='' sanitizers_pid='' container_pid=''
}
while [ -n "$ctest_pid$checks_pid$sanitizers_pid$container_pid" ]; do
  finished=
  status=0
  # shellcheck disable=SC2086  # the pids still running, one to four
  wait -n -p finished $ctest_pid $checks_pid $sanitizers_pid $container_pid || status=$?
  if [ "$finished" = "$ctest_pid" ]; then
    ctest_pid=
    if [ "$status" -ne 0 ]; then
      took "ctest (build-asan) FAILED" "$step"
      [ -z "$checks_pid$sanitizers_pid$container_pid" ] || echo "test.sh: ctest failed: the lanes beside it are stopped" >&2
      stop_lanes
      record_checks
      exit "$status"
    fi
    took "ctest (build-asan), -j $test_jobs" "$step"
    ctest_ended_at=$SECONDS
    touch "$checks/ctest-ended"
  elif [ -n "$finished" ] && [ "$status" -ne 0 ]; then
    if [ -n "$ctest_pid" ]; then
      echo "test.sh: an item beside ctest failed: ctest is stopped" >&2
      took "ctest (build-asan), stopped" "$step"
    fi
    stop_lanes
    record_checks
    exit 1
  elif [ "$finished" = "$checks_pid" ]; then
    checks_pid=
  elif [ "$finished" = "$sanitizers_pid" ]; then
    sanitizers_pid=
  elif [ "$finished" = "$container_pid" ]; then
    container_pid=
  fi
done
trap summary EXIT
took "the lanes beside it, after ctest" "${ctest_ended_at:-$SECONDS}"
record_checks
# ARM, light form (docs/ARM.md "In the test command"): the protocol and modbus_map suites cross-built
# for armhf (32-bit ARMv7: 32-bit long, size_t and time_t; unsigned char) and run under qemu-arm,
# on a machine where scripts/cross.sh finds its cross toolchain, qemu and the armhf sysroot ready.
# The test command does not install them: `scripts/cross.sh armhf --deps-only` takes several
# minutes and a few hundred MB, which a fresh CI machine would pay on every run (README "The two commands").
if [ "${SMS_SKIP_ARM:-0}" != 1 ]; then
  if arm_ready=$(./scripts/cross.sh armhf --ready 2>&1); then
    step=$SECONDS
    ./scripts/cross.sh armhf --test-light --suites protocol_tests,modbus_map_tests || { took "ARM light step FAILED" "$step"; exit 1; }
    took "ARM light step" "$step"
  else
    echo "test.sh: ARM light step not run: ${arm_ready##*: } (scripts/cross.sh armhf --deps-only installs it)"
  fi
fi
