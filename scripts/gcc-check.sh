#!/usr/bin/env bash
# GCC 12's front end over every file of the default build (product, tests, benchmarks), with the
# build's own flags and warnings as errors: what the test command checks of the compiler of
# packagers, scripts/bench.sh and the container image (docs/DECISIONS.md "GCC in the test
# command"). The sources the build generates are made first. A file that passed and has not
# changed is not checked again (check_once.py).
#   scripts/gcc-check.sh [BUILD_DIR]   a GCC build configured by scripts/test.sh (default build-gcc)
exec "$(dirname "$0")/check_once.py" gcc "${1:-build-gcc}"
