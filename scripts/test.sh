#!/usr/bin/env bash
# The one command that runs every test: installs dependencies, builds with
# AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/, runs ctest; then builds the
# libFuzzer targets with clang into build-fuzz/ and runs each briefly (SMS_SKIP_FUZZ=1 skips them;
# scripts/fuzz.sh is the longer run).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
jobs=$(nproc)
cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=Debug -DSMS_SANITIZE=ON -DSMS_BUILD_BENCH=OFF >/dev/null
cmake --build build-asan -j "$jobs"
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
ctest --test-dir build-asan --output-on-failure -j "$jobs" "$@"
if [ "${SMS_SKIP_FUZZ:-0}" != 1 ]; then
  ./scripts/fuzz.sh --build
  ctest --test-dir build-fuzz --output-on-failure -j "$jobs" "$@"
fi
