#!/usr/bin/env bash
# Debian's own checks of the package (on demand; root for piuparts; minutes):
#   lintian --pedantic   must report no error and no warning (overrides only with their reason
#                        in debian/sms-gateway.lintian-overrides);
#   piuparts             installs, removes and purges it in a clean Debian 12 chroot made by
#                        debootstrap from the machine's apt mirror, and fails on anything left
#                        behind or any maintainer-script error.
# The test command checks the package in a light form (tests/package/package_test.sh);
# scripts/systemd-test.sh checks the unit under a real systemd.
#
#   scripts/package-check.sh [DEB]   # default: build it with scripts/package.sh into build-deb/
set -euo pipefail
cd "$(dirname "$0")/.."
deb=${1:-}
if [ -z "$deb" ]; then
  ./scripts/package.sh build-deb
  deb=$(ls -t build-deb/sms-gateway_*_*.deb | grep -v dbgsym | head -1)
fi
[ -f "$deb" ] || { echo "package-check: no such package: $deb" >&2; exit 1; }
sudo_cmd=()
[ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
for p in lintian piuparts debootstrap; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" ||
    DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "$p" >/dev/null
done

status=0
echo "package-check: lintian --pedantic $(basename "$deb")"
# lintian warns that it runs as root; that line is not about the package.
if ! lintian --pedantic --display-info --tag-display-limit 0 --fail-on error,warning "$deb" \
     2> >(grep -v 'running with root privileges' >&2); then
  echo "package-check: lintian found errors or warnings (above)" >&2
  status=1
fi

mirror=$(awk '/^URIs:/ { print $2; exit }' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
mirror=${mirror:-http://deb.debian.org/debian}
echo "package-check: piuparts (bookworm from $mirror)"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if "${sudo_cmd[@]}" piuparts --distribution=bookworm --mirror="$mirror main" \
     --extra-repo="deb $mirror bookworm-updates main" --log-file="$log" "$deb" >/dev/null 2>&1; then
  grep -E 'INFO: (PASS|Can.t test upgrade)' "$log" || true
else
  grep -E 'ERROR|FAIL' "$log" | head -30 >&2
  mkdir -p build-deb && cp "$log" build-deb/piuparts.log
  echo "package-check: piuparts failed (full log: build-deb/piuparts.log)" >&2
  status=1
fi
[ "$status" -eq 0 ] && echo "package-check: lintian and piuparts passed"
exit "$status"
