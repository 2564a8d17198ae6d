#!/usr/bin/env bash
# GCC 12's front end over every file of the default build (product, tests, benchmarks), with the
# build's own flags and warnings as errors: what the test command checks of the compiler of
# packagers, scripts/bench.sh and the container image (docs/DECISIONS.md "GCC in the test
# command"). A file that passed and has not changed is not checked again (check_once.py).
#   scripts/gcc-check.sh [BUILD_DIR]   BUILD_DIR: a GCC build configured by scripts/test.sh (default build-gcc)
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build-gcc}
if [ ! -f "$build/compile_commands.json" ]; then
  echo "gcc-check: $build/compile_commands.json is missing: configure $build first (scripts/test.sh does)" >&2
  exit 2
fi
# Sources the build generates (the protobuf code, the console's embedded pages) are made first.
mapfile -t generated < <(/usr/bin/python3 -c '
import json, os, sys
build = os.path.abspath(sys.argv[1])
for e in json.load(open(os.path.join(build, "compile_commands.json"))):
    path = os.path.abspath(os.path.join(e["directory"], e["file"]))
    if path.startswith(build + "/"):
        print(os.path.relpath(path, build))' "$build")
[ "${#generated[@]}" -eq 0 ] || cmake --build "$build" --target "${generated[@]}" >/dev/null
mapfile -t files < <(/usr/bin/python3 -c '
import json, os, sys
for e in json.load(open(os.path.join(sys.argv[1], "compile_commands.json"))):
    print(os.path.abspath(os.path.join(e["directory"], e["file"])))' "$build")
exec "$(dirname "$0")/check_once.py" gcc "$build" "${files[@]}"
