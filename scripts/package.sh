#!/usr/bin/env bash
# Builds the Debian package the way Debian does: `dpkg-buildpackage -b -us -uc` on debian/
# (debhelper, CMake, the dpkg-buildflags hardening flags; a Release-like build with GCC 12 in
# obj-<triplet>/), then copies the .deb files to the output directory (default: build-deb/).
# The test command checks the same rules in a light form (tests/package/package_test.sh);
# scripts/package-check.sh runs lintian and piuparts on the result.
#
#   scripts/package.sh [OUTPUT_DIR]              # OUTPUT_DIR/sms-gateway_VERSION_ARCH.deb
#   scripts/package.sh --install [OUTPUT_DIR]    # ... and `apt-get install` it here (root or sudo)
#   scripts/package.sh --arch arm64 [OUTPUT_DIR] # the same packaging cross-built for arm64 or armhf
#                                                # (dpkg-buildpackage -a ARCH, through scripts/cross.sh)
set -euo pipefail
cd "$(dirname "$0")/.."

install=0 out= arch=
while [ $# -gt 0 ]; do
  case "$1" in
    --install) install=1 ;;
    --arch) [ $# -ge 2 ] || { echo "package.sh: --arch needs an architecture (arm64, armhf)" >&2; exit 2; }
            arch=$2; shift ;;
    -h|--help) sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    -*) echo "package.sh: unknown option '$1' (try --help)" >&2; exit 2 ;;
    *) [ -z "$out" ] || { echo "package.sh: one output directory, not '$out' and '$1'" >&2; exit 2; }
       out=$1 ;;
  esac
  shift
done
out=${out:-build-deb}

# A cross build: scripts/cross.sh installs the cross toolchain and the target's libraries (or makes
# its sysroot), checks the target's build dependencies, and comes back here with SMS_CROSS_PREPARED.
native=$(dpkg --print-architecture)
[ "${arch:-$native}" != "$native" ] || arch=
if [ -n "$arch" ]; then
  ((install == 0)) || { echo "package.sh: --install installs on this $native machine: not with --arch $arch" >&2; exit 2; }
  [ -n "${SMS_CROSS_PREPARED:-}" ] || exec ./scripts/cross.sh "$arch" --deb "$out"
fi

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
work=$PWD/build-deb/work${arch:+-$arch}
rm -rf "$work" && mkdir -p "$work/src"
echo "package.sh: copying the sources to $work/src"
git ls-files -z --cached --others --exclude-standard | xargs -0 cp --parents -t "$work/src" 2>/dev/null ||
  tar --exclude='./build*' --exclude=./.git -cf - . | tar -xf - -C "$work/src"
# Cross: the architecture-dependent package only (-B), no tests (nocheck: they run under qemu in
# scripts/cross.sh --test), and -d: dpkg-checkbuilddeps cannot see what cross.sh provides outside
# dpkg (the sysroot, the unpacked -dev package that is not co-installable); cross.sh checked it.
# ccache, when installed, in front of the compilers (CMake reads these variables; the fixed path
# above lets it hit across runs). A cross build's toolchain settings come from cross.sh.
if command -v ccache >/dev/null; then
  export CMAKE_C_COMPILER_LAUNCHER=${CMAKE_C_COMPILER_LAUNCHER:-ccache}
  export CMAKE_CXX_COMPILER_LAUNCHER=${CMAKE_CXX_COMPILER_LAUNCHER:-ccache}
fi
started=$SECONDS
build=(dpkg-buildpackage -b -us -uc -j"$(nproc)")
[ -z "$arch" ] ||
  build=(env DEB_BUILD_OPTIONS="nocheck ${DEB_BUILD_OPTIONS:-}" dpkg-buildpackage -a "$arch" -B -d -us -uc -j"${SMS_CROSS_JOBS:-2}")
# The build's output goes to its log; what it is doing is said as it goes: each debhelper step
# as it starts, and during the compile ninja's [done/all] once a minute (a native build is about
# 20 minutes of GCC -O2 on 2 cores, a cross build more).
log=$work/build.log
say_progress() {
  local said='' said_at=$SECONDS step progress
  while sleep 2; do
    # "   dh_auto_build -O--buildsystem=cmake+ninja" and the like: dh names each step as it starts it.
    step=$(sed -n 's/^   \(dh_[a-z_]*\).*/\1/p' "$log" | tail -1)
    progress=$(tail -c 65536 "$log" | grep -o '^\[[0-9]*/[0-9]*\]' | tail -1 || true)
    if [ -n "$step" ] && [ "$step" != "$said" ]; then
      echo "package.sh: $step (after $((SECONDS - started)) s)"
      said=$step said_at=$SECONDS
    elif [ -n "$progress" ] && ((SECONDS - said_at >= 60)); then
      echo "package.sh: $step: compiled $progress (after $((SECONDS - started)) s)"
      said_at=$SECONDS
    fi
  done
}
echo "package.sh: ${build[*]} in $work/src (log: $log)"
: >"$log"
say_progress &
speaker=$!
trap 'kill "$speaker" 2>/dev/null || true' EXIT
(cd "$work/src" && "${build[@]}") >"$log" 2>&1 ||
  { tail -50 "$log" >&2; echo "package.sh: dpkg-buildpackage failed ($log)" >&2; exit 1; }
kill "$speaker" 2>/dev/null || true
echo "package.sh: built in $((SECONDS - started)) s"
mkdir -p "$out"
cp "$work"/*.deb "$work"/*.buildinfo "$work"/*.changes "$out"/
deb=$(ls "$out"/sms-gateway_*_"${arch:-$native}".deb | head -1)
echo "package.sh: $deb"
if ((install)); then
  "${sudo_cmd[@]}" apt-get install -y "$(realpath "$deb")"
fi
