#!/usr/bin/env bash
# Builds the Debian package the way a packager would: a Release build with GCC 12 in
# build-release/ (installs to /usr), then `cpack -G DEB`. The test command checks the same
# package rules in a light form (tests/package/package_test.sh).
#
#   scripts/package.sh              # build-release/sms-gateway_VERSION_ARCH.deb
#   scripts/package.sh --install    # ... and `apt-get install` it on this machine (root or sudo)
set -euo pipefail
cd "$(dirname "$0")/.."

install=0
case "${1:-}" in
  "") ;;
  --install) install=1 ;;
  -h|--help) sed -n '2,8p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  *) echo "package.sh: unknown argument '$1' (try --help)" >&2; exit 2 ;;
esac

./scripts/install-deps.sh
cmake -S . -B build-release -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX=/usr \
  -DSMS_BUILD_TESTS=OFF -DSMS_BUILD_BENCH=OFF >/dev/null
cmake --build build-release --target sms-gateway sms-sim -j "$(nproc)"
(cd build-release && cpack -G DEB)
deb=$(ls build-release/sms-gateway_*_*.deb | head -1)
echo "package.sh: $deb"
if ((install)); then
  sudo_cmd=()
  [ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
  "${sudo_cmd[@]}" apt-get install -y "./$deb"
fi
