#!/usr/bin/env bash
# libFuzzer runs of tests/fuzz (clang, ASan + UBSan), built in build-fuzz/.
#
#   scripts/fuzz.sh TARGET [SECONDS] [libFuzzer options...]   fuzz one target, default 300 s
#   scripts/fuzz.sh all [SECONDS]                             every target in turn
#   scripts/fuzz.sh --list                                    the targets
#   scripts/fuzz.sh --build                                   configure and build only (scripts/test.sh)
#
# A run starts from the seed corpus tests/fuzz/corpus/TARGET/ plus the scratch corpus
# build-fuzz/fuzz-corpus/TARGET/ (kept between runs; new inputs land there). A crash or a broken
# invariant is written to tests/fuzz/crashes/TARGET-crash-<sha1> and the run stops. Replay one with
#   build-fuzz/bin/TARGET tests/fuzz/crashes/TARGET-crash-<sha1>
# and, once fixed, move it into tests/fuzz/corpus/TARGET/ so every test run replays it.
set -euo pipefail
cd "$(dirname "$0")/.."

build_dir=build-fuzz

build() {
  cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER=clang++ \
    -DSMS_SANITIZE=ON -DSMS_FUZZ=ON -DSMS_BUILD_TESTS=OFF -DSMS_BUILD_BENCH=OFF -DSMS_WERROR=ON \
    -DCMAKE_UNITY_BUILD=ON >/dev/null
  # Only the fuzzers and what they link: the rest of the tree is built and tested in build-asan/.
  cmake --build "$build_dir" --target sms_fuzzers -j "$(nproc)"
}

targets() {
  find "$build_dir/bin" -maxdepth 1 -name 'fuzz_*' -type f -perm -u+x -printf '%f\n' | sort
}

run() {
  local target=$1 seconds=$2
  shift 2
  local binary=$build_dir/bin/$target
  if [ ! -x "$binary" ]; then
    echo "fuzz.sh: no fuzz target '$target'; the targets are:" >&2
    targets >&2
    exit 2
  fi
  local scratch=$build_dir/fuzz-corpus/$target
  local dictionary=()
  [ -f "tests/fuzz/dict/$target.dict" ] && dictionary=(-dict="tests/fuzz/dict/$target.dict")
  mkdir -p "$scratch" tests/fuzz/crashes
  echo "fuzz.sh: $target for $seconds s (new inputs: $scratch, crashes: tests/fuzz/crashes/)" >&2
  ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
    "$binary" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -malloc_limit_mb=32 -print_final_stats=1 "${dictionary[@]}" \
    -artifact_prefix="tests/fuzz/crashes/$target-" "$@" "$scratch" "tests/fuzz/corpus/$target"
}

case "${1:-}" in
  "" | -h | --help)
    sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
    exit 2
    ;;
  --build)
    build
    ;;
  --list)
    build >/dev/null
    targets
    ;;
  all)
    build
    for target in $(targets); do run "$target" "${2:-300}"; done
    ;;
  *)
    build
    target=$1
    seconds=${2:-300}
    shift $(($# < 2 ? $# : 2))
    run "$target" "$seconds" "$@"
    ;;
esac
