#!/usr/bin/env bash
# Builds the release build in build/ (RelWithDebInfo, benchmarks on, tests off), then runs every
# benchmark in bench/ and prints its figures as `name value unit` lines (`#` lines are context).
# Benchmarks only print; they talk to 127.0.0.1 only and stop by themselves.
#
#   scripts/bench.sh            # everything, the soak for 60 s (about 3 minutes in all)
#   scripts/bench.sh --quick    # shorter runs, the soak for 10 s (about 1 minute)
#   scripts/bench.sh soak       # only the named programs (bench/programs.txt lists them)
#   SMS_BUILD_DIR=build-bench scripts/bench.sh   # another build directory (default build)
#
# Figures depend on the machine and on what else runs on it: compare a run with itself, not
# with another machine. The README's "Performance (measured)" section has a reference run.
set -euo pipefail
cd "$(dirname "$0")/.."

# The programs and the options of their shortest runs: bench/programs.txt.
programs=()
declare -A quick_options=()
while read -r program options; do
  programs+=("$program")
  quick_options[$program]=$options
done < <(grep -E '^[a-z_]+' bench/programs.txt)
quick=0
selected=()
for argument in "$@"; do
  case "$argument" in
    --quick) quick=1 ;;
    -h|--help) sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) if [ -n "${quick_options[$argument]+set}" ]; then selected+=("$argument"); else
         echo "bench.sh: unknown argument '$argument' (try --help; programs: ${programs[*]})" >&2; exit 2; fi ;;
  esac
done
if ((${#selected[@]} > 0)); then programs=("${selected[@]}"); fi

build_dir="${SMS_BUILD_DIR:-build}"
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSMS_BUILD_TESTS=OFF -DSMS_BUILD_BENCH=ON -DSMS_WERROR=ON \
  -DSMS_SANITIZE=OFF >/dev/null
cmake --build "$build_dir" --target sms-gateway "${programs[@]}" -j "$(nproc)"

echo "# $(date -u '+%Y-%m-%d %H:%M UTC'), $(nproc) cores, $(uname -m), load average $(cut -d' ' -f1-3 /proc/loadavg)"
status=0
for program in "${programs[@]}"; do
  echo "# --- $program"
  options=()
  if ((quick)); then read -r -a options <<<"${quick_options[$program]}"; fi
  if ! "$build_dir/bin/$program" "${options[@]}"; then
    echo "# $program FAILED" >&2
    status=1
  fi
done
exit "$status"
