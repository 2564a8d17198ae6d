#!/usr/bin/env bash
# Installs every build, test and tool dependency from Debian 12 packages.
# Idempotent and quiet when everything is already there, so the run and test
# commands can call it every time.
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config dpkg-dev
  libboost-dev libmodbus-dev libspdlog-dev libfmt-dev libyaml-cpp-dev
  libcli11-dev libgtest-dev libgmock-dev libssl-dev openssl
  libmosquitto-dev mosquitto libprotobuf-dev protobuf-compiler
  clang libclang-rt-14-dev clang-format clang-tidy ccache lld
  mbpoll socat python3-pymodbus python3-serial python3-serial-asyncio stress-ng
  debhelper help2man pandoc man-db
  tshark  # reads the bus monitor's captures (tests/gateway/monitor); wireshark-common's debconf question takes its default
  libsodium-dev nlohmann-json3-dev libjs-chart.js chromium chromium-driver python3-selenium
  prometheus python3-yaml  # promtool checks and tests the shipped alert rules (deploy/prometheus)
)

missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0

echo "install-deps: installing ${missing[*]}" >&2
sudo_cmd=()
[ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
export DEBIAN_FRONTEND=noninteractive
"${sudo_cmd[@]}" apt-get update -qq
"${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
