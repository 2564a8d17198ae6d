#!/usr/bin/env bash
# The suites on a loaded machine (on demand): ctest over build-asan/ (made by scripts/test.sh)
# ROUNDS times in a row (default 3), as many tests at once as the test command runs
# (SMS_TEST_JOBS, default 3 a core), with `stress-ng --cpu N --io M` (default: one CPU worker per
# core and one I/O worker) busy beside it the whole time. Every suite waits for what the
# simulator shows, not for a time window, so it must pass as it does on an idle machine; a
# failure names the test and the round.
#
#   scripts/test-under-load.sh [ROUNDS] [ctest arguments...]     # e.g. 3 -R Safety
#   SMS_STRESS_CPUS=4 SMS_STRESS_IO=2 scripts/test-under-load.sh # more load
set -euo pipefail
cd "$(dirname "$0")/.."
rounds=${1:-3}
shift || true
[ -f build-asan/CTestTestfile.cmake ] || { echo "test-under-load: no build-asan/: run scripts/test.sh first" >&2; exit 1; }
command -v stress-ng >/dev/null || { echo "test-under-load: stress-ng is missing (apt-get install stress-ng)" >&2; exit 1; }
cpus=${SMS_STRESS_CPUS:-$(nproc)}
io=${SMS_STRESS_IO:-1}
test_jobs=${SMS_TEST_JOBS:-$((3 * $(nproc)))}
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
stress-ng --cpu "$cpus" --io "$io" --timeout 0 --quiet &
stress=$!
trap 'kill "$stress" 2>/dev/null || true; wait "$stress" 2>/dev/null || true' EXIT
sleep 2
status=0
for round in $(seq "$rounds"); do
  start=$(date +%s)
  echo "test-under-load: round $round of $rounds, stress-ng --cpu $cpus --io $io beside ctest -j $test_jobs on $(nproc) cores; load $(cut -d' ' -f1-3 /proc/loadavg)"
  if ctest --test-dir build-asan --output-on-failure -j "$test_jobs" "$@" >"build-asan/under-load-$round.log" 2>&1; then
    echo "test-under-load: round $round passed in $(( $(date +%s) - start )) s: $(grep -m1 'tests passed' "build-asan/under-load-$round.log"); load $(cut -d' ' -f1-3 /proc/loadavg)"
  else
    status=1
    echo "test-under-load: round $round FAILED in $(( $(date +%s) - start )) s (build-asan/under-load-$round.log):"
    sed -n '/The following tests FAILED/,$p' "build-asan/under-load-$round.log"
  fi
done
exit "$status"
