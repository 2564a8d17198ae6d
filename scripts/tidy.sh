#!/usr/bin/env bash
# clang-tidy (.clang-tidy at the root) over the product's sources: protocol/, modbus_map/,
# config/, gateway/, simulator/ — with their headers (HeaderFilterRegex). Tests and benchmarks
# are not checked: gtest's macros trip bugprone-* without finding anything.
#   scripts/tidy.sh [BUILD_DIR]   BUILD_DIR has compile_commands.json (default build-asan)
# Exits 1 on any finding (WarningsAsErrors: '*'), naming file, line and check. A file that
# passed and has not changed (nor its headers, flags or .clang-tidy) is not checked again
# (check_once.py).
exec "$(dirname "$0")/check_once.py" tidy "${1:-build-asan}"
