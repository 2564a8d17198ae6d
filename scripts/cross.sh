#!/usr/bin/env bash
# Cross builds for the ARM edge boxes on this amd64 machine, with Debian's own cross toolchains
# (crossbuild-essential-ARCH) and the target's Debian -dev packages; the tests run under Debian's
# qemu-user-static. Nothing is downloaded but Debian packages. docs/ARM.md explains the choices.
#
#   scripts/cross.sh ARCH                 # ARCH = arm64 | armhf: cross-configure and build into build-ARCH/
#   scripts/cross.sh ARCH --test          # ... and run the unit tests under qemu (all folders)
#   scripts/cross.sh ARCH --test-light    # ... only the protocol, modbus_map and config suites (the light form)
#   ... --suites protocol_tests,modbus_map_tests   # with --test-light: only these (the test command's form)
#   scripts/cross.sh ARCH --simulate      # ... and check sms-gateway under qemu answers Modbus reads from the host
#   scripts/cross.sh ARCH --deb OUTDIR    # ... and build the Debian package sms-gateway_VERSION_ARCH.deb into OUTDIR
#                                         # from debian/ (dpkg-buildpackage -a ARCH; scripts/package.sh --arch ARCH)
#   scripts/cross.sh ARCH --deps-only     # only install what the cross build needs (idempotent)
#   scripts/cross.sh ARCH --ready         # exit 0 if all that is installed already, else 1 and what is missing
#
# Options combine (--test --simulate --deb out). Where the target's libraries come from:
#   arm64: multiarch packages (dpkg --add-architecture arm64; /usr/lib/aarch64-linux-gnu);
#   armhf: a sysroot made from the armhf packages (/var/cache/sms-gateway-cross/armhf), because
#          the armhf multiarch packages cannot be installed consistently here (docs/ARM.md).
# SMS_CROSS_MODE=multiarch|sysroot overrides that; SMS_CROSS_CACHE moves the sysroot cache.
set -euo pipefail
# One compound command: bash reads all of it before running it, so editing this file during a long
# build cannot disturb a run.
{
cd "$(dirname "$0")/.."
repo=$PWD

usage() { sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; }
arch=${1:-}
case "$arch" in
  arm64) triplet=aarch64-linux-gnu; qemu=qemu-aarch64-static; binfmt=qemu-aarch64; default_mode=multiarch ;;
  armhf) triplet=arm-linux-gnueabihf; qemu=qemu-arm-static; binfmt=qemu-arm; default_mode=sysroot ;;
  -h|--help) usage; exit 0 ;;
  *) echo "cross.sh: first argument must be arm64 or armhf (try --help)" >&2; exit 2 ;;
esac
shift
run_tests=none deb_dir= deps_only=0 simulate=0 ready_only=0 light_suites=(protocol_tests modbus_map_tests config_tests)
while [ "$#" -gt 0 ]; do
  case "$1" in
    --test) run_tests=all ;;
    --test-light) run_tests=light ;;
    --simulate) simulate=1 ;;
    --deb) [ "$#" -ge 2 ] || { echo "cross.sh: --deb needs an output directory" >&2; exit 2; }
           mkdir -p "$2"; deb_dir=$(cd "$2" && pwd); shift ;;
    --deps-only) deps_only=1 ;;
    --ready) ready_only=1 ;;
    --suites) [ "$#" -ge 2 ] || { echo "cross.sh: --suites needs a list (protocol_tests,modbus_map_tests)" >&2; exit 2; }
              IFS=, read -r -a light_suites <<<"$2"; shift ;;
    *) echo "cross.sh: unknown argument '$1' (try --help)" >&2; exit 2 ;;
  esac
  shift
done
mode=${SMS_CROSS_MODE:-$default_mode}
cache=${SMS_CROSS_CACHE:-/var/cache/sms-gateway-cross}
build=$repo/build-$arch
sudo_cmd=()
[ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
log() { echo "cross.sh [$arch]: $*" >&2; }
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

# The target's libraries the project builds and links against (the -dev packages of
# scripts/install-deps.sh, for the target). libcli11-dev and the Boost headers are the same for
# every architecture but are looked up per architecture all the same.
target_dev_packages=(libboost-dev libmodbus-dev libspdlog-dev libfmt-dev libyaml-cpp-dev libssl-dev
                     libmosquitto-dev libprotobuf-dev libgtest-dev libgmock-dev libsodium-dev nlohmann-json3-dev)
# Debian 12's libyaml-cpp-dev is not "Multi-Arch: same": the arm64 one would replace the amd64 one
# the native build needs. Its runtime library is co-installable; the -dev package is unpacked into
# a prefix of its own instead (SMS_CROSS_PREFIXES).
not_coinstallable=(libyaml-cpp-dev)

# --ready: stop at the first thing that would have to be installed or made.
not_ready() { ((ready_only)) || return 0; log "not ready: $*"; exit 1; }
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
apt_install() {
  "${sudo_cmd[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o DPkg::Lock::Timeout=600 \
    --no-install-recommends "$@" >/dev/null
}

# --- the build machine's part: cross compiler, qemu, protoc --------------------------------------
host_packages=(crossbuild-essential-"$arch" qemu-user-static cmake ninja-build pkg-config dpkg-dev
               protobuf-compiler mbpoll)
missing=()
for p in "${host_packages[@]}"; do installed "$p" || missing+=("$p"); done
if [ ${#missing[@]} -gt 0 ]; then
  not_ready "${missing[*]} not installed"
  log "installing ${missing[*]}"
  "${sudo_cmd[@]}" apt-get update -qq -o DPkg::Lock::Timeout=600
  apt_install "${missing[@]}"
fi

prefixes=()
if [ "$mode" = multiarch ]; then
  # --- the target's libraries as multiarch packages ----------------------------------------------
  if ! dpkg --print-foreign-architectures | grep -qx "$arch"; then
    not_ready "dpkg has no $arch architecture"
    log "dpkg --add-architecture $arch"
    "${sudo_cmd[@]}" dpkg --add-architecture "$arch"
    "${sudo_cmd[@]}" apt-get update -qq -o DPkg::Lock::Timeout=600 \
      || { "${sudo_cmd[@]}" dpkg --remove-architecture "$arch"
           log "apt-get update fails with $arch added (the mirror's $arch index?): architecture removed again;" \
               "SMS_CROSS_MODE=sysroot builds without it"; exit 1; }
  fi
  missing=()
  for p in "${target_dev_packages[@]}"; do
    if [[ " ${not_coinstallable[*]} " == *" $p "* ]]; then continue; fi
    installed "$p:$arch" || missing+=("$p:$arch")
  done
  installed "libyaml-cpp0.7:$arch" || missing+=("libyaml-cpp0.7:$arch")
  # The target's pkg-config (/usr/bin/TRIPLET-pkg-config), which debhelper's cross build calls.
  installed "pkgconf:$arch" || missing+=("pkgconf:$arch")
  if [ ${#missing[@]} -gt 0 ]; then
    not_ready "${missing[*]} not installed"
    log "installing ${missing[*]}"
    apt_install "${missing[@]}"
  fi
  for p in "${not_coinstallable[@]}"; do
    dir=$cache/$arch/prefix-$p
    version=$(apt-cache policy "$p:$arch" | awk '/Candidate:/ { print $2 }')
    if [ "$(cat "$dir/.version" 2>/dev/null)" != "$version" ]; then
      not_ready "$p:$arch $version not unpacked into $dir"
      log "unpacking $p:$arch $version into $dir"
      rm -rf "$dir" && mkdir -p "$dir/debs"
      (cd "$dir/debs" && apt-get download -qq -o APT::Sandbox::User=root "$p:$arch=$version")
      dpkg-deb -x "$dir"/debs/*.deb "$dir"
      # Its CMake files name the shared library next to them: link the installed runtime package's.
      for runtime in $(dpkg-deb -f "$dir"/debs/*.deb Depends | tr ',' '\n' | awk '{ print $1 }'); do
        installed "$runtime:$arch" || continue
        dpkg -L "$runtime:$arch" | grep "^/usr/lib/$triplet/.*\.so" | while read -r file; do
          [ -e "$dir$file" ] || ln -s "$file" "$dir$file"
        done
      done
      echo "$version" >"$dir/.version"
    fi
    prefixes+=("$dir/usr")
  done
else
  # --- the target's libraries in a sysroot: apt resolves and downloads the target's packages with
  # a state of its own (the machine's dpkg and apt configuration are left alone), dpkg-deb unpacks
  # them. Each library package is also unpacked on its own with its control files (symbols,
  # shlibs): dpkg-shlibdeps reads the package's dependency information from there.
  root=$cache/$arch
  sysroot=$root/sysroot
  # Also what multiarch takes from the build machine: the compiler's own C and C++ libraries (with
  # a sysroot it looks for nothing outside it) and the architecture-independent CLI11 headers.
  sysroot_packages=("${target_dev_packages[@]}" libc6-dev libstdc++-12-dev libcli11-dev)
  want="${sysroot_packages[*]}"
  if [ "$(cat "$root/.packages" 2>/dev/null)" != "$want" ]; then
    not_ready "no $arch sysroot in $sysroot"
    log "making the $arch sysroot in $sysroot"
    rm -rf "$root" && mkdir -p "$root/apt/lists/partial" "$root/apt/cache/archives/partial" "$sysroot" "$root/packages"
    : >"$root/apt/status"
    cat >"$root/apt/apt.conf" <<APT
#clear APT::Architectures;
APT::Architecture "$arch";
APT::Architectures { "$arch"; };
Dir::State "$root/apt";
Dir::State::status "$root/apt/status";
Dir::Cache "$root/apt/cache";
Debug::NoLocking "true";
APT
    # An index the mirror serves inconsistently is left out (apt says which); the rest is used.
    APT_CONFIG=$root/apt/apt.conf apt-get update -qq || log "apt-get update: some $arch indexes failed (above); using the others"
    APT_CONFIG=$root/apt/apt.conf apt-get install -y -qq --download-only --no-install-recommends \
      "${sysroot_packages[@]}" >/dev/null
    for deb in "$root"/apt/cache/archives/*.deb; do
      dpkg-deb -x "$deb" "$sysroot"
      package=$(dpkg-deb -f "$deb" Package)
      case "$package" in
        *-dev|*-doc|*-common|libc-dev-bin|linux-libc-dev) ;;
        *) dpkg-deb -x "$deb" "$root/packages/$package"; dpkg-deb -e "$deb" "$root/packages/$package/DEBIAN" ;;
      esac
    done
    rm -rf "$root/apt/cache/archives"
    echo "$want" >"$root/.packages"
  fi
  export SMS_CROSS_SYSROOT=$sysroot
  # Child processes the tests start (sms-sim, sms-gateway) find the target's loader through this.
  export QEMU_LD_PREFIX=$sysroot
fi
export SMS_CROSS_PREFIXES="${prefixes[*]}"
if ((ready_only)); then log "ready: the cross toolchain, qemu and the $arch libraries are installed"; exit 0; fi

# --- running ARM programs: qemu directly, and through binfmt_misc for the programs the tests
# start themselves. qemu-user-static's entries have the F flag (the interpreter is opened when
# registered), so podman can run arm64 images with them too.
binfmt_ready() { [ -e "/proc/sys/fs/binfmt_misc/$binfmt" ]; }
if ! binfmt_ready && { [ "$run_tests" = all ] || ((deps_only)); }; then
  if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
    "${sudo_cmd[@]}" mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>/dev/null || true
  fi
  if [ -w /proc/sys/fs/binfmt_misc/register ] && [ -f "/usr/lib/binfmt.d/$binfmt.conf" ]; then
    "${sudo_cmd[@]}" sh -c "cat /usr/lib/binfmt.d/$binfmt.conf > /proc/sys/fs/binfmt_misc/register" 2>/dev/null || true
  fi
  binfmt_ready && log "registered $binfmt with binfmt_misc (qemu-user-static)" \
    || log "binfmt_misc not available: tests that start ARM programs themselves cannot run here"
fi
((deps_only)) && exit 0

# --- configure -----------------------------------------------------------------------------------
# ccache when it is installed (its settings from the environment, CCACHE_DIR and so on).
launcher=()
command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
cmake -S . -B "$build" -G Ninja -DCMAKE_TOOLCHAIN_FILE="$repo/cmake/toolchains/$triplet.cmake" \
  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_INSTALL_PREFIX=/usr -DSMS_WERROR=ON -DSMS_BUILD_BENCH=OFF \
  "${launcher[@]}" >/dev/null
build_targets() {
  local t0
  t0=$(now)
  cmake --build "$build" -j "${SMS_CROSS_JOBS:-2}" -t "$@"
  log "built $* in $(elapsed "$t0") s"
}

# --- unit tests under qemu: each suite's binary once (one emulator start per suite, not per case) -
emulator=("$qemu")
[ "$mode" = sysroot ] && emulator+=(-L "$sysroot")
failed=0
run_suites() {
  local name t0
  for name in "$@"; do
    t0=$(now)
    if "${emulator[@]}" "$build/tests/$name" --gtest_brief=1; then
      log "$name passed under $qemu in $(elapsed "$t0") s"
    else
      log "$name FAILED under $qemu"
      failed=1
    fi
  done
}
# The light suites first: they are what the test command runs, and they need no program.
programs=(sms-gateway sms-sim)
if [ "$run_tests" = none ] && [ -z "$deb_dir" ] && ((simulate == 0)); then
  build_targets "${light_suites[@]}" "${programs[@]}"
fi
if [ "$run_tests" != none ]; then
  build_targets "${light_suites[@]}"
  run_suites "${light_suites[@]}"
fi
# With --deb, --simulate checks the packaged sms-gateway instead of building build-ARCH's.
if [ "$run_tests" = all ] || { ((simulate)) && [ -z "$deb_dir" ]; }; then
  build_targets "${programs[@]}"
fi
gateway_program=$build/bin/sms-gateway gateway_label="sms-gateway (build-$arch)"

# --- the Debian package: debian/ cross-built by scripts/package.sh (dpkg-buildpackage -a ARCH -B,
# debian/rules adding the toolchain file). dpkg-buildpackage runs with -d, as dpkg-checkbuilddeps
# cannot see what this script provides outside dpkg; checked here instead: every build dependency
# it finds unmet must be one this script provides (the sysroot's packages, or the -dev package that
# is not co-installable, unpacked into its prefix). dpkg-shlibdeps looks the target's libraries up
# in the multiarch packages; in sysroot mode, in each library package unpacked with its DEBIAN/
# (symbols, shlibs): SMS_DEB_SHLIBS_DIRS, given to dh_shlibdeps -l.
build_deb() {
  local unmet provided p missing=() t0
  if [ "$mode" = multiarch ]; then provided=("${not_coinstallable[@]}"); else provided=("${sysroot_packages[@]}"); fi
  unmet=$(dpkg-checkbuilddeps -a "$arch" 2>&1 | sed -n 's/.*Unmet build dependencies: //p' | sed 's/([^)]*)//g; s/|//g' || true)
  for p in $unmet; do
    [[ " ${provided[*]} " == *" ${p%%:*} "* ]] || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    log "--deb: build dependencies missing for $arch: ${missing[*]} (debian/control; this script provides ${provided[*]})"
    exit 1
  fi
  export SMS_DEB_SHLIBS_DIRS=
  if [ "$mode" = sysroot ]; then
    SMS_DEB_SHLIBS_DIRS=$(find "$root/packages" -type d -path "*/lib/$triplet" -printf '%p:' | sed 's/:$//')
  fi
  t0=$(now)
  SMS_CROSS_PREPARED=1 scripts/package.sh --arch "$arch" "$deb_dir" >/dev/null
  log "dpkg-buildpackage -a $arch -B (build-deb/work-$arch) in $(elapsed "$t0") s"
}
if [ -n "$deb_dir" ]; then
  rm -f "$deb_dir"/sms-gateway_*_"$arch".deb
  build_deb
  deb=$(ls "$deb_dir"/sms-gateway_*_"$arch".deb)
  log "$deb: Architecture $(dpkg-deb -f "$deb" Architecture); Depends: $(dpkg-deb -f "$deb" Depends)"
  gateway_program=$build/sms-gateway.from-deb gateway_label="sms-gateway (from $(basename "$deb"))"
  dpkg-deb --fsys-tarfile "$deb" | tar -xOf - ./usr/bin/sms-gateway >"$gateway_program"
  chmod +x "$gateway_program"
  log "$deb: usr/bin/sms-gateway: $(file -b "$gateway_program" | cut -d, -f1-2)"
fi

# --- the gateway under qemu answers Modbus from the host ------------------------------------------
# `sms-gateway --simulate` (6 sts servos at 1000000 bit/s on an in-process pty) under qemu: qemu-user
# has no termios2, and the pty is left without a rate (gateway/bus/termios2_io.h). Mbpoll from the
# host reads the version from unit 255, sees the servos online, writes a goal position and reads it
# back, watches the simulated servo reach it; SIGTERM then stops the gateway with status 0.
free_port() { /usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
# read_registers PORT UNIT TYPE FIRST COUNT -> the values on one line (mbpoll -t 3 input, 4 holding)
read_registers() {
  mbpoll -m tcp -p "$1" -a "$2" -0 -t "$3" -r "$4" -c "$5" -1 -o 1 127.0.0.1 2>/dev/null \
    | awk '/^\[[0-9]+\]:/ { printf "%s%s", sep, $2; sep = " " } END { print "" }'
}
wait_value() {  # wait_value SECONDS WANT PORT UNIT TYPE FIRST COUNT
  local deadline=$(( $(date +%s) + $1 )) want=$2 got
  shift 2
  until got=$(read_registers "$@") && [ "$got" = "$want" ]; do
    [ "$(date +%s)" -lt "$deadline" ] || { echo "$got"; return 1; }
    sleep 0.2
  done
}
simulate_check() {
  local want port t0 first pid ok=1 why= unit goal status
  want=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' CMakeLists.txt | tr . ' ')
  port=$(free_port)
  t0=$(now)
  "${emulator[@]}" "$gateway_program" --simulate --listen "127.0.0.1:$port" >"$build/simulate.log" 2>&1 &
  pid=$!
  # Stopped however this function ends (a check failing, the script interrupted).
  trap 'kill $pid 2>/dev/null || true' EXIT
  if ! wait_value 60 "$want" "$port" 255 3 0 3 >/dev/null; then
    ok=0 why="no version from unit 255 within 60 s"
  else
    first=$(elapsed "$t0")
    for unit in 1 2 3 4 5 6; do
      wait_value 20 1 "$port" "$unit" 3 1001 1 >/dev/null || { ok=0 why="servo unit $unit not online"; }
    done
  fi
  if ((ok)); then
    # Re-arm the watchdog (coil 2 of unit 255 := 0; README "Try it"), then goal position
    # (holding 42) := 3000 on unit 1; the simulated servo moves there (present position, input 56).
    mbpoll -m tcp -p "$port" -a 255 -0 -t 0 -r 2 -1 -o 1 127.0.0.1 0 >/dev/null 2>&1 || { ok=0 why="re-arming the watchdog"; }
    mbpoll -m tcp -p "$port" -a 1 -0 -t 4 -r 42 -1 -o 1 127.0.0.1 3000 >/dev/null 2>&1 || { ok=0 why="FC06 goal position 3000 to unit 1"; }
    goal=$(read_registers "$port" 1 4 42 1)
    [ "$goal" = 3000 ] || { ok=0 why="unit 1 goal position reads '$goal' after writing 3000"; }
    wait_value 30 3000 "$port" 1 3 56 1 >/dev/null || { ok=0 why="unit 1 present position did not reach 3000 within 30 s"; }
  fi
  kill -TERM "$pid" 2>/dev/null || true
  status=0
  wait "$pid" || status=$?
  trap - EXIT
  if ((ok)) && [ "$status" = 0 ]; then
    log "$gateway_label --simulate under $qemu: unit 255 input registers 0-2 = $want (the version) after $first s;" \
        "servo units 1-6 online; FC06 goal position 3000 to unit 1 read back, present position reached it;" \
        "SIGTERM: exit status 0"
  else
    tail -20 "$build/simulate.log" >&2
    log "$gateway_label --simulate under $qemu: FAILED: ${why:-exit status $status after SIGTERM} (log: $build/simulate.log)"
    failed=1
  fi
}
((simulate)) && simulate_check

# --- the suites that run serial lines on ptys; their tests also start sms-sim and sms-gateway
# (through binfmt_misc). A case whose failure carries the error of a termios2 call failed only
# because qemu-user cannot set its rate (above); it is counted apart. Any other failure fails.
run_line_suites() {
  local name t0 json
  for name in "$@"; do
    t0=$(now)
    json=$build/$name.json
    rm -f "$json"
    "${emulator[@]}" "$build/tests/$name" --gtest_brief=1 --gtest_output="json:$json" >"$build/$name.log" 2>&1 || true
    if [ ! -s "$json" ]; then
      tail -20 "$build/$name.log" >&2
      log "$name FAILED under $qemu: it stopped before reporting (log: $build/$name.log)"
      failed=1
      continue
    fi
    if ! /usr/bin/python3 - "$json" "$name" "$qemu" "$(elapsed "$t0")" <<'PY' >&2
import json, re, sys
path, name, qemu, seconds = sys.argv[1:]
# The errno texts of a termios2 call under qemu-user (7.2: ENOSYS, 10.0: ENOTTY), as the product's
# and the tests' own serial code word them.
rate = re.compile(r"(Function not implemented|Inappropriate ioctl for device)")
passed, emulator, other = 0, [], []
for suite in json.load(open(path))["testsuites"]:
    for case in suite["testsuite"]:
        if case.get("result") == "SKIPPED" or case.get("status") == "NOTRUN":
            continue
        failures = case.get("failures", [])
        full = suite["name"] + "." + case["name"]
        if not failures:
            passed += 1
        elif any(rate.search(f.get("failure", "")) for f in failures):
            emulator.append(full)
        else:
            other.append(full)
print(f"cross.sh: {name} under {qemu} in {seconds} s: {passed} passed, {len(emulator)} failed only on a termios2 call "
      f"qemu-user does not emulate, {len(other)} other failures" + ("".join("\n  " + o for o in other)))
sys.exit(1 if other else 0)
PY
    then
      failed=1
    fi
  done
}
if [ "$run_tests" = all ]; then
  if binfmt_ready; then
    build_targets simulator_tests gateway_tests
    # gateway_tests builds one test program per gateway library (tests/gateway/*/).
    run_line_suites simulator_tests gateway_bus_tests gateway_modbus_tcp_tests gateway_units_tests \
      gateway_observability_tests gateway_tools_tests gateway_rtu_slave_tests
  else
    log "simulator_tests and gateway_tests not run: they start ARM programs, which needs binfmt_misc"
    failed=1
  fi
fi
exit $failed
}
