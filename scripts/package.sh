#!/usr/bin/env bash
# Builds the Debian package the way Debian does: `dpkg-buildpackage -b -us -uc` on debian/
# (debhelper, CMake, the dpkg-buildflags hardening flags; a Release-like build with GCC 12 in
# obj-<triplet>/), then copies the .deb files to the output directory (default: build-deb/).
# The test command checks the same rules in a light form (tests/package/package_test.sh);
# scripts/package-check.sh runs lintian and piuparts on the result.
#
#   scripts/package.sh [OUTPUT_DIR]              # OUTPUT_DIR/sms-gateway_VERSION_ARCH.deb
#   scripts/package.sh --install [OUTPUT_DIR]    # ... and `apt-get install` it here (root or sudo)
set -euo pipefail
cd "$(dirname "$0")/.."

install=0 out=
while [ $# -gt 0 ]; do
  case "$1" in
    --install) install=1 ;;
    -h|--help) sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    -*) echo "package.sh: unknown option '$1' (try --help)" >&2; exit 2 ;;
    *) [ -z "$out" ] || { echo "package.sh: one output directory, not '$out' and '$1'" >&2; exit 2; }
       out=$1 ;;
  esac
  shift
done
out=${out:-build-deb}

./scripts/install-deps.sh
sudo_cmd=()
[ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
# dpkg-buildpackage's own tools (debhelper); the Build-Depends of debian/control are checked by it.
for p in debhelper dpkg-dev; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" ||
    DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "$p" >/dev/null
done

# dpkg-buildpackage writes its results next to the source tree: it builds a copy of the committed
# files plus the working tree's changes in build-deb/work/src (a fixed path, so ccache can hit),
# and neither the tree nor its parent collects build files.
work=$PWD/build-deb/work
rm -rf "$work" && mkdir -p "$work/src"
git ls-files -z --cached --others --exclude-standard | xargs -0 cp --parents -t "$work/src" 2>/dev/null ||
  tar --exclude='./build*' --exclude=./.git -cf - . | tar -xf - -C "$work/src"
(cd "$work/src" && dpkg-buildpackage -b -us -uc -j"$(nproc)") >"$work/build.log" 2>&1 ||
  { tail -50 "$work/build.log" >&2; echo "package.sh: dpkg-buildpackage failed ($work/build.log)" >&2; exit 1; }
mkdir -p "$out"
cp "$work"/*.deb "$work"/*.buildinfo "$work"/*.changes "$out"/
deb=$(ls "$out"/sms-gateway_*_*.deb | grep -v dbgsym | head -1)
echo "package.sh: $deb"
if ((install)); then
  "${sudo_cmd[@]}" apt-get install -y "$(realpath "$deb")"
fi
