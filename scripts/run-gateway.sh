#!/usr/bin/env bash
# The README's run command: installs the Debian 12 packages, builds the gateway and the
# simulator (release build in build/), then runs the gateway on its embedded default — a
# simulated bus of 6 sts servos (units 1-6) — serving Modbus TCP on 127.0.0.1:5020.
# Extra arguments go to sms-gateway, e.g. --listen 0.0.0.0:5020 or --log-level debug.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
# A unity build (sources compiled in batches of 8) takes about half the CPU of one file at a time.
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSMS_BUILD_TESTS=OFF -DCMAKE_UNITY_BUILD=ON >/dev/null
cmake --build build --target sms-gateway sms-sim -j "$(nproc)"
exec build/bin/sms-gateway --simulate "$@"
