#!/usr/bin/env bash
# Container check (root; a few minutes, most of it the image's compile). The test command runs it
# with --head where podman is installed:
# builds docker/Dockerfile with podman (daemonless, no registry needed) and runs the image the
# way the README says, checking each claim the README makes about it. Prints what it checked.
#
#   ./scripts/container-test.sh            # build context = the working tree
#   ./scripts/container-test.sh --head     # build context = the committed HEAD (git archive)
#   ./scripts/container-test.sh --context DIR   # build context = DIR (e.g. an unpacked release)
#   ... --no-cache                          # rebuild every layer (apt steps included): cold build time
#   ... --build-only                        # build the image and stop (the test command builds it beside
#                                           # ctest at low priority; the checking run then finds every layer built)
#   ./scripts/container-test.sh --arm64    # instead: docker/Dockerfile.cross for linux/arm64, run under
#                                          # qemu-user-static (binfmt_misc); says so where podman cannot
#
# Exits 0 with "skipped: podman not available" when podman is missing.
# Environment: SMS_CONTAINER_DIR (default /tmp/ctr) holds podman's storage and configuration
# unless CONTAINERS_CONF / CONTAINERS_STORAGE_CONF are set: overlay storage there, runc as the
# runtime (crun fails on hybrid cgroups), raised ulimits.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD

if ! command -v podman >/dev/null 2>&1; then
  echo "container-test: skipped: podman not available (apt-get install podman buildah debootstrap runc)"
  exit 0
fi
# The runtime podman is configured with below (crun fails on hybrid cgroups) and the init that
# `podman run --init` puts in the container: podman only recommends them, so an install without
# recommends lacks them.
for need in runc:/usr/sbin/runc catatonit:/usr/libexec/podman/catatonit; do
  if [ ! -x "${need#*:}" ]; then
    echo "container-test: installing ${need%%:*} (podman's runtime and its --init here)" >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need%%:*}" >/dev/null \
      || { echo "container-test: ${need%%:*} is missing and could not be installed (apt-get install ${need%%:*})" >&2; exit 1; }
  fi
done
if ! command -v mbpoll >/dev/null 2>&1; then
  echo "container-test: mbpoll is needed for the Modbus reads from the host: run scripts/install-deps.sh" >&2
  exit 1
fi

context_mode=worktree
build_only=0
platform=amd64
build_options=()
context=$repo
while [ "$#" -gt 0 ]; do
  case "$1" in
    --head) context_mode="head" ;;
    --no-cache) build_options+=(--no-cache) ;;
    --build-only) build_only=1 ;;
    --arm64) platform=arm64 ;;
    --context) [ "$#" -ge 2 ] || { echo "usage: $0 [--head | --context DIR] [--no-cache] [--build-only]" >&2; exit 2; }
               context_mode="directory $2"; context=$(cd "$2" && pwd); shift ;;
    *) echo "usage: $0 [--head | --context DIR] [--no-cache] [--build-only] [--arm64]" >&2; exit 2 ;;
  esac
  shift
done

image=localhost/sms-gateway:container-test
run_id=sms-ctr-test-$$
containers=()
sim_pid=
tmp=$(mktemp -d)
work=${SMS_CONTAINER_DIR:-/tmp/ctr}
# debootstrap mounts /proc and more inside the root it makes, and leaves them mounted when it
# fails or is interrupted; a later run would then fail inside debootstrap with a confusing message.
unmount_under() {
  local dir=$1 target
  [ -d "$dir" ] || return 0
  dir=$(cd "$dir" && pwd -P)
  findmnt -rn -o TARGET | awk -v d="$dir" 'index($0, d "/") == 1 || $0 == d' | sort -r |
    while read -r target; do umount -l "$target" 2>/dev/null || true; done
}
cleanup() {
  local c
  for c in "${containers[@]}"; do podman rm -f -t 0 "$c" >/dev/null 2>&1 || true; done
  if [ -n "$sim_pid" ]; then kill "$sim_pid" 2>/dev/null || true; fi
  unmount_under "$work/rootfs"
  unmount_under "$work/rootfs-arm64"
  # --one-file-system: never into a mount that could not be undone.
  rm -rf --one-file-system "$tmp" "$work/rootfs" "$work/rootfs-arm64"
}
trap cleanup EXIT

# The image's compiler cache (docker/Dockerfile uses one mounted at /ccache), beside podman's
# storage: a rebuild compiles only the files that changed. --no-cache measures the cold build
# without it. compile_cache_stats: what the last build found there, for its check line.
compile_cache=()
if [[ " ${build_options[*]} " != *" --no-cache "* ]]; then
  mkdir -p "$work/ccache"
  compile_cache=(--volume "$work/ccache:/ccache")
  command -v ccache >/dev/null && CCACHE_DIR=$work/ccache ccache --zero-stats >/dev/null
fi
compile_cache_stats() {
  [ "${#compile_cache[@]}" -gt 0 ] || { echo "no compiler cache"; return; }
  command -v ccache >/dev/null || { echo "compiler cache in $work/ccache"; return; }
  CCACHE_DIR=$work/ccache ccache --print-stats | awk -F'\t' '
    $1 == "direct_cache_hit" || $1 == "preprocessed_cache_hit" { hit += $2 } $1 == "cache_miss" { miss = $2 }
    END { printf "compiler cache: %d of %d files found", hit, hit + miss }'
}

checks=()
check() { checks+=("ok    $*"); echo "container-test: ok: $*"; }
fail() { echo "container-test: FAILED: $*" >&2; exit 1; }
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
free_port() { /usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

# Modbus read from the host: read_input_registers PORT UNIT FIRST COUNT -> values on one line.
read_input_registers() {
  local out
  out=$(mbpoll -m tcp -p "$1" -a "$2" -0 -t 3 -r "$3" -c "$4" -1 -o 1 127.0.0.1 2>&1) || return 1
  awk '/^\[[0-9]+\]:/ { printf "%s%s", sep, $2; sep = " " } END { print "" }' <<<"$out"
}
# wait_for_modbus PORT UNIT SECONDS [REGISTER [VALUE]]: until the unit answers a read of that
# input register (default 0), with that value when one is given.
wait_for_modbus() {
  local deadline=$(( $(date +%s) + $3 )) got
  until got=$(read_input_registers "$1" "$2" "${4:-0}" 1) && { [ -z "${5:-}" ] || [ "$got" = "$5" ]; }; do
    [ "$(date +%s)" -lt "$deadline" ] || return 1
    sleep 0.2
  done
}
# start_container ARGS...: podman run -d; its chatter (no systemd to time health checks) goes to a
# log shown only when the start fails.
start_container() {
  podman run -d "$@" >/dev/null 2>"$tmp/podman-run.log" || { cat "$tmp/podman-run.log" >&2; fail "podman run -d $*"; }
}
# stop_and_check NAME WHAT: SIGTERM via podman stop; must exit 0 well before podman's SIGKILL.
stop_and_check() {
  local t0 secs code
  t0=$(now)
  podman stop -t 10 "$1" >/dev/null
  secs=$(elapsed "$t0")
  code=$(podman inspect --format '{{.State.ExitCode}}' "$1")
  [ "$code" = 0 ] || { podman logs "$1" | tail -20 >&2; fail "$2: exit code $code after SIGTERM (want 0)"; }
  awk -v s="$secs" 'BEGIN { exit !(s < 10) }' || fail "$2: stop took ${secs} s (want < 10 s)"
  check "$2: SIGTERM -> exit 0 in ${secs} s"
}

# Without systemd, podman reports on stderr for every container with a HEALTHCHECK that it cannot
# arm a timer for it (health checks then run only through `podman healthcheck run`). Harmless here.
podman() { command podman "$@" 2> >(grep -v 'unable to get systemd connection' >&2); }

# --- podman environment: its own storage and configuration under $work -------------------------
if [ -z "${CONTAINERS_CONF:-}" ]; then
  mkdir -p "$work/conf"
  if [ ! -f "$work/conf/containers.conf" ]; then
    # root cannot raise hard limits here, and crun fails on hybrid cgroups.
    printf '[containers]\ndefault_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]\n[engine]\nruntime = "runc"\n' \
      > "$work/conf/containers.conf"
    printf '[storage]\ndriver = "overlay"\ngraphroot = "%s/storage"\nrunroot = "%s/runroot"\n' \
      "$work" "$work" > "$work/conf/storage.conf"
  fi
  export CONTAINERS_CONF=$work/conf/containers.conf CONTAINERS_STORAGE_CONF=$work/conf/storage.conf
fi

total_t0=$(now)
if ! podman image exists docker.io/library/debian:bookworm; then
  # No registry needed: a minimal Debian 12 root from the machine's own apt mirror.
  command -v debootstrap >/dev/null || fail "no debian:bookworm image and no debootstrap to make one"
  t0=$(now)
  mirror=$(awk '/^URIs:/ { print $2; exit }' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
  rootfs=$work/rootfs
  unmount_under "$rootfs"
  rm -rf --one-file-system "$rootfs"
  debootstrap --variant=minbase bookworm "$rootfs" "${mirror:-http://deb.debian.org/debian}" >"$tmp/debootstrap.log" 2>&1 \
    || { tail -20 "$tmp/debootstrap.log" >&2; fail "debootstrap of the base image"; }
  unmount_under "$rootfs"
  chroot "$rootfs" apt-get clean
  if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    cp /etc/apt/sources.list.d/debian.sources "$rootfs/etc/apt/sources.list.d/" && rm -f "$rootfs/etc/apt/sources.list"
  fi
  tar -C "$rootfs" -c . | podman import --change 'CMD ["bash"]' - docker.io/library/debian:bookworm >/dev/null
  rm -rf --one-file-system "$rootfs"
  check "base image debian:bookworm made with debootstrap in $(elapsed "$t0") s"
fi
podman image exists docker.io/library/debian:bookworm-slim \
  || podman tag docker.io/library/debian:bookworm docker.io/library/debian:bookworm-slim

# --- the arm64 image (--arm64): cross compiled on this machine, run under emulation (docs/ARM.md) --
if [ "$platform" = arm64 ]; then
  # podman runs an arm64 image's programs through the kernel's binfmt_misc entry for qemu-aarch64;
  # qemu-user-static's entry has the F flag (interpreter opened at registration), which a
  # container needs, since it has no qemu of its own.
  entry=/proc/sys/fs/binfmt_misc/qemu-aarch64
  if [ ! -e "$entry" ] && [ -f /usr/lib/binfmt.d/qemu-aarch64.conf ]; then
    [ -e /proc/sys/fs/binfmt_misc/register ] || mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>/dev/null || true
    cat /usr/lib/binfmt.d/qemu-aarch64.conf >/proc/sys/fs/binfmt_misc/register 2>/dev/null || true
  fi
  if ! grep -q '^flags:.*F' "$entry" 2>/dev/null; then
    echo "container-test: skipped: podman cannot run arm64 images here: no binfmt_misc entry for qemu-aarch64 with the F flag" \
         "(apt-get install qemu-user-static; binfmt_misc must be mountable: not in an unprivileged container)"
    exit 0
  fi
  check "podman can run arm64 programs: binfmt_misc qemu-aarch64 ($(sed -n 's/^interpreter //p' "$entry"), flags $(sed -n 's/^flags: //p' "$entry"))"

  # The target's Debian 12 without a registry: debootstrap runs its second stage under qemu.
  arm_base=localhost/debian-arm64:bookworm-slim
  if ! podman image exists "$arm_base"; then
    t0=$(now)
    mirror=$(awk '/^URIs:/ { print $2; exit }' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
    rootfs=$work/rootfs-arm64
    unmount_under "$rootfs"
    rm -rf --one-file-system "$rootfs"
    debootstrap --arch=arm64 --variant=minbase bookworm "$rootfs" "${mirror:-http://deb.debian.org/debian}" >"$tmp/debootstrap.log" 2>&1 \
      || { tail -20 "$tmp/debootstrap.log" >&2; fail "debootstrap --arch=arm64 of the base image"; }
    unmount_under "$rootfs"
  chroot "$rootfs" apt-get clean
    if [ -f /etc/apt/sources.list.d/debian.sources ]; then
      cp /etc/apt/sources.list.d/debian.sources "$rootfs/etc/apt/sources.list.d/" && rm -f "$rootfs/etc/apt/sources.list"
    fi
    tar -C "$rootfs" -c . | podman import --arch arm64 --change 'CMD ["bash"]' - "$arm_base" >/dev/null
    rm -rf --one-file-system "$rootfs"
    check "arm64 base image $arm_base made with debootstrap under qemu in $(elapsed "$t0") s"
  fi
  if [ "$context_mode" = head ]; then
    context=$tmp/context
    mkdir -p "$context"
    git -C "$repo" archive HEAD | tar -x -C "$context"
  fi
  image=localhost/sms-gateway:container-test-arm64
  t0=$(now)
  # BUILDPLATFORM and TARGETPLATFORM spelt out: podman 4.3 leaves the first empty (docker/Dockerfile.cross).
  podman build "${build_options[@]}" "${compile_cache[@]}" --pull=never --platform linux/arm64 --build-arg BUILDPLATFORM="linux/$(dpkg --print-architecture)" \
    --build-arg TARGETPLATFORM=linux/arm64 --build-arg RUNTIME_BASE="$arm_base" --format docker \
    -f "$context/docker/Dockerfile.cross" -t "$image" "$context" >"$tmp/build.log" 2>&1 \
    || { tail -40 "$tmp/build.log" >&2; fail "podman build --platform linux/arm64 -f docker/Dockerfile.cross"; }
  check "arm64 image built from the $context_mode in $(elapsed "$t0") s (build stage amd64, cross compiled, $(compile_cache_stats); $(podman image inspect --format '{{.Size}}' "$image" | awk '{ printf "%.0f MB", $1 / 1e6 }'))"

  arch=$(podman image inspect --format '{{.Architecture}}' "$image")
  [ "$arch" = arm64 ] || fail "image architecture is '$arch', want arm64"
  machine=$(podman run --rm --health-cmd none --entrypoint uname "$image" -m)
  [ "$machine" = aarch64 ] || fail "uname -m in the container says '$machine', want aarch64"
  extract_ctr=$run_id-extract
  containers+=("$extract_ctr")
  podman create --health-cmd none --name "$extract_ctr" "$image" >/dev/null
  podman cp "$extract_ctr:/usr/local/bin/sms-gateway" "$tmp/sms-gateway"
  podman rm "$extract_ctr" >/dev/null
  elf=$(file -b "$tmp/sms-gateway")
  case "$elf" in *"ARM aarch64"*) ;; *) fail "the image's sms-gateway is not an ARM aarch64 program: $elf" ;; esac
  check "image architecture arm64, uname -m aarch64 under emulation; sms-gateway: ${elf%%, BuildID*}"

  want_version=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' "$context/CMakeLists.txt")
  got_version=$(podman run --rm --health-cmd none "$image" --version)
  grep -qF "$want_version" <<<"$got_version" || fail "'--version' says '$got_version', CMakeLists.txt says $want_version"
  check "entrypoint passes options to sms-gateway: --version -> $got_version"

  # The default command: the simulated bus (6 sts servos at 1000000 bit/s on an in-process pty).
  # qemu-user has no termios2, so that pty is left without a rate, which a pty does not need
  # (gateway/bus/termios2_io.h; docs/ARM.md).
  sim_ctr=$run_id-arm64-simulate
  containers+=("$sim_ctr")
  port=$(free_port)
  t0=$(now)
  # Hardened as in docker-compose.yml (and the amd64 check below): non-root on 502, read-only, no capabilities.
  start_container --init --name "$sim_ctr" -p "127.0.0.1:$port:502" --read-only --tmpfs /tmp --cap-drop ALL \
    --security-opt no-new-privileges --sysctl net.ipv4.ip_unprivileged_port_start=0 "$image"
  wait_for_modbus "$port" 255 60 || { podman logs "$sim_ctr" | tail -20 >&2; fail "arm64 default command: no Modbus answer from unit 255 within 60 s"; }
  first=$(elapsed "$t0")
  for unit in 1 2 3 4 5 6; do
    wait_for_modbus "$port" "$unit" 20 1001 1 || { podman logs "$sim_ctr" | tail -20 >&2; fail "arm64 default command: simulated servo unit $unit not online"; }
  done
  check "arm64 default command under emulation (sms-gateway --simulate: 6 sts servos at 1000000 bit/s on a pty): first Modbus answer from the host after $first s (non-root, read-only, no capabilities); servo units 1-6 online"
  stop_and_check "$sim_ctr" "arm64 default command, with --init"

  # The image's own sms-sim (arm64, on the host through binfmt) on a pty at 115200 bit/s, mounted
  # as /dev/ttyUSB0 with a config for that rate, as the amd64 serial check does.
  extract_ctr=$run_id-extract-sim
  containers+=("$extract_ctr")
  podman create --health-cmd none --name "$extract_ctr" "$image" >/dev/null
  podman cp "$extract_ctr:/usr/local/bin/sms-sim" "$tmp/sms-sim"
  podman rm "$extract_ctr" >/dev/null
  "$tmp/sms-sim" --protocol feetech --table sts --ids 1-3 --baud 115200 --link "$tmp/ttySIM0" >"$tmp/sim.log" 2>&1 &
  sim_pid=$!
  for _ in $(seq 100); do [ -e "$tmp/ttySIM0" ] && break; sleep 0.1; done
  [ -e "$tmp/ttySIM0" ] || { cat "$tmp/sim.log" >&2; fail "arm64 sms-sim made no pty link"; }
  pts=$(readlink -f "$tmp/ttySIM0")
  chown root:dialout "$pts" && chmod 0660 "$pts"
  printf 'buses:\n  - {name: adapter, device: /dev/ttyUSB0, protocol: feetech, baud: 115200}\nservos:\n' >"$tmp/config.yaml"
  for unit in 1 2 3; do printf '  - {bus: adapter, id: %s, table: sts}\n' "$unit" >>"$tmp/config.yaml"; done
  chmod 0644 "$tmp/config.yaml"
  port=$(free_port)
  serial_ctr=$run_id-arm64-serial
  containers+=("$serial_ctr")
  t0=$(now)
  start_container --init --name "$serial_ctr" -p "127.0.0.1:$port:502" -v "$pts:/dev/ttyUSB0" \
    -v "$tmp/config.yaml:/etc/sms-gateway/config.yaml:ro" --read-only --tmpfs /tmp --cap-drop ALL \
    --security-opt no-new-privileges --sysctl net.ipv4.ip_unprivileged_port_start=0 "$image"
  wait_for_modbus "$port" 255 60 || { podman logs "$serial_ctr" | tail -20 >&2; fail "arm64: no Modbus answer from unit 255 within 60 s"; }
  first=$(elapsed "$t0")
  want_registers=$(tr '.' ' ' <<<"$want_version")
  got_registers=$(read_input_registers "$port" 255 0 3) || fail "arm64: reading input registers 0-2 of unit 255"
  [ "$got_registers" = "$want_registers" ] || fail "arm64: unit 255 input registers 0-2 = '$got_registers', want '$want_registers'"
  for unit in 1 2 3; do
    wait_for_modbus "$port" "$unit" 20 1001 1 || { podman logs "$serial_ctr" | tail -20 >&2; fail "arm64: servo unit $unit on the pty not online"; }
  done
  mbpoll -m tcp -p "$port" -a 2 -0 -t 4 -r 42 -1 -o 1 127.0.0.1 1234 >"$tmp/write.log" 2>&1 \
    || { cat "$tmp/write.log" >&2; fail "arm64: FC06 write of goal position 1234 to unit 2"; }
  goal=$(mbpoll -m tcp -p "$port" -a 2 -0 -t 4 -r 42 -c 1 -1 -o 1 127.0.0.1 | awk '/^\[42\]:/ { print $2 }')
  [ "$goal" = 1234 ] || fail "arm64: unit 2 holding register 42 reads '$goal' after writing 1234"
  check "arm64 gateway (config mounted, /dev/ttyUSB0 = pty of the image's sms-sim at 115200 bit/s): first Modbus answer from the host after $first s; unit 255 input registers 0-2 = $got_registers; servo units 1-3 online; FC06 goal position 1234 acknowledged and read back"
  podman healthcheck run "$serial_ctr" >/dev/null || fail "arm64: podman healthcheck run reports unhealthy"
  check "arm64: podman healthcheck run: healthy"
  stop_and_check "$serial_ctr" "arm64, with --init"

  echo
  echo "container-test: arm64 image passed in $(elapsed "$total_t0") s. Checked:"
  printf '  %s\n' "${checks[@]}"
  echo "Not checked here: the arm64 image on ARM hardware, the armhf image (same Dockerfile, --platform linux/arm/v7)."
  exit 0
fi

# --- build -------------------------------------------------------------------------------------
if [ "$context_mode" = head ]; then
  context=$tmp/context
  mkdir -p "$context"
  git -C "$repo" archive HEAD | tar -x -C "$context"
fi
t0=$(now)
# Each line of the build log gets the second it appeared, for the time of each step.
podman build "${build_options[@]}" "${compile_cache[@]}" --format docker -f "$context/docker/Dockerfile" -t "$image" "$context" 2>&1 \
  | while IFS= read -r line; do printf '%(%s)T %s\n' -1 "$line"; done >"$tmp/build.log" \
  || { tail -40 "$tmp/build.log" >&2; fail "podman build (context: $context_mode)"; }
# seconds from the step whose instruction matches $1 to the next step
step_seconds() {
  awk -v pattern="$1" '/ STEP [0-9]+\/[0-9]+: / { if (t) { print $1 - t; exit } if ($0 ~ pattern) t = $1 }' "$tmp/build.log"
}
check "image built from the $context_mode${build_options:+ (${build_options[*]})} in $(elapsed "$t0") s ($(podman image inspect --format '{{.Size}}' "$image" | awk '{ printf "%.0f MB", $1 / 1e6 }'));" \
  "build-stage apt $(step_seconds 'RUN apt-get') s, compile $(step_seconds 'cmake --build') s ($(compile_cache_stats))"
if [ "$build_only" = 1 ]; then
  echo "container-test: image built (--build-only): nothing run or checked"
  exit 0
fi

# --- what the image declares and contains ------------------------------------------------------
[ "$(podman image inspect --format '{{.Config.User}}' "$image")" = "sms" ] || fail "image USER is not sms"
podman image inspect --format '{{json .Config.ExposedPorts}}' "$image" | grep -q '"502/tcp"' || fail "image does not EXPOSE 502"
podman image inspect --format '{{json .Config.Healthcheck}}' "$image" | grep -q mbpoll || fail "image has no HEALTHCHECK (built without --format docker?)"
check "image metadata: USER sms, EXPOSE 502/tcp, HEALTHCHECK kept"

ids=$(podman run --rm --health-cmd none --entrypoint id "$image")
case "$ids" in *"uid=502(sms)"*"dialout"*) ;; *) fail "container user: $ids";; esac
check "container runs as $ids"

podman run --rm --health-cmd none --entrypoint dpkg-query "$image" -W -f '${Package}\n' >"$tmp/packages"
if grep -E -- '-dev$|^(g\+\+|gcc|cpp|cmake|ninja-build)(-[0-9]+)?$' "$tmp/packages" >"$tmp/build-packages"; then
  fail "runtime image holds build packages: $(tr '\n' ' ' <"$tmp/build-packages")"
fi
check "runtime image has no compiler, cmake or -dev package ($(wc -l <"$tmp/packages") packages)"

want_version=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' "$context/CMakeLists.txt")
got_version=$(podman run --rm --health-cmd none "$image" --version)
grep -qF "$want_version" <<<"$got_version" || fail "'--version' says '$got_version', CMakeLists.txt says $want_version"
check "entrypoint passes options to sms-gateway: --version -> $got_version"

for example in $(podman run --rm --health-cmd none --entrypoint ls "$image" /usr/share/doc/sms-gateway/examples); do
  podman run --rm --health-cmd none "$image" --check-config "/usr/share/doc/sms-gateway/examples/$example" \
    >"$tmp/check.log" 2>&1 || { cat "$tmp/check.log" >&2; fail "--check-config of the shipped example $example"; }
  shipped_examples="${shipped_examples:-}${shipped_examples:+, }$example"
done
[ -n "${shipped_examples:-}" ] || fail "no example configs in /usr/share/doc/sms-gateway/examples"
check "shipped example configs pass --check-config: $shipped_examples"

# --- the simulated bus, hardened as in docker-compose.yml ----------------------------------------
hardening=(--read-only --tmpfs /tmp --cap-drop ALL --security-opt no-new-privileges
           --sysctl net.ipv4.ip_unprivileged_port_start=0)
port=$(free_port)
sim_ctr=$run_id-sim
containers+=("$sim_ctr")
t0=$(now)
start_container --init --name "$sim_ctr" -p "127.0.0.1:$port:502" "${hardening[@]}" "$image"
wait_for_modbus "$port" 255 30 || { podman logs "$sim_ctr" | tail -20 >&2; fail "no Modbus answer from unit 255 within 30 s"; }
check "no config mounted -> simulated bus; first Modbus answer from the host after $(elapsed "$t0") s (port $port -> 502, non-root, read-only, no capabilities)"

want_registers=$(tr '.' ' ' <<<"$want_version")
got_registers=$(read_input_registers "$port" 255 0 3) || fail "reading input registers 0-2 of unit 255"
[ "$got_registers" = "$want_registers" ] || fail "unit 255 input registers 0-2 = '$got_registers', want '$want_registers'"
check "Modbus read from the host (mbpoll): unit 255 input registers 0-2 = $got_registers (the version)"

# Servo units answer from the poll cache once discovery has found them online.
wait_for_modbus "$port" 1 10 1001 1 || fail "simulated servo unit 1 not online (input register 1001 != 1 after 10 s)"
position=$(read_input_registers "$port" 1 56 1) || fail "reading input register 56 (present position) of simulated servo unit 1"
check "simulated servo unit 1 online (input register 1001 = 1), present position (56) = $position"

t0=$(now)
podman healthcheck run "$sim_ctr" >/dev/null || fail "podman healthcheck run reports unhealthy"
check "podman healthcheck run: healthy ($(elapsed "$t0") s)"

# The health check must be able to fail: a gateway that serves, but not on port 502.
other_port=$(free_port)
off_ctr=$run_id-offport
containers+=("$off_ctr")
start_container --name "$off_ctr" -p "127.0.0.1:$other_port:5020" -e SMS_GATEWAY_LISTEN=0.0.0.0:5020 "$image"
wait_for_modbus "$other_port" 255 30 || { podman logs "$off_ctr" | tail -20 >&2; fail "gateway on 5020 did not answer"; }
if podman healthcheck run "$off_ctr" >/dev/null 2>&1; then
  fail "healthcheck says healthy although nothing answers on port 502"
fi
check "SMS_GATEWAY_LISTEN=0.0.0.0:5020 moves the listener; the healthcheck then reports unhealthy"

stop_and_check "$sim_ctr" "with --init"
stop_and_check "$off_ctr" "without --init (sms-gateway is PID 1)"

# --- a mounted config and a serial device --------------------------------------------------------
# The image's own sms-sim runs on the host on a pty made to look like a USB adapter (root:dialout
# 0660, as udev leaves /dev/ttyUSB0); the pty goes in as /dev/ttyUSB0 and the config is mounted
# at /etc/sms-gateway/config.yaml. Its listen address is deliberately not 502: the image's
# SMS_GATEWAY_LISTEN must win.
extract_ctr=$run_id-extract
containers+=("$extract_ctr")
podman create --health-cmd none --name "$extract_ctr" "$image" >/dev/null
podman cp "$extract_ctr:/usr/local/bin/sms-sim" "$tmp/sms-sim"
podman cp "$extract_ctr:/usr/local/bin/sms-gateway" "$tmp/sms-gateway"
podman rm "$extract_ctr" >/dev/null
if ! "$tmp/sms-sim" --help >/dev/null 2>&1; then
  echo "container-test: the image's sms-sim does not run on this host (runtime libraries?); serial part not checked" >&2
  serial_checked=no
else
  serial_checked=yes
  "$tmp/sms-sim" --protocol feetech --table sts --ids 1-3 --baud 1000000 --link "$tmp/ttySIM0" >"$tmp/sim.log" 2>&1 &
  sim_pid=$!
  for _ in $(seq 50); do [ -e "$tmp/ttySIM0" ] && break; sleep 0.1; done
  [ -e "$tmp/ttySIM0" ] || { cat "$tmp/sim.log" >&2; fail "sms-sim made no pty link"; }
  pts=$(readlink -f "$tmp/ttySIM0")
  chown root:dialout "$pts" && chmod 0660 "$pts"
  cat >"$tmp/config.yaml" <<'YAML'
modbus_tcp:
  listen: 127.0.0.1:5020
buses:
  - name: adapter
    device: /dev/ttyUSB0
    protocol: feetech
    baud: 1000000
servos:
  - {bus: adapter, id: 1, table: sts}
  - {bus: adapter, id: 2, table: sts}
  - {bus: adapter, id: 3, table: sts}
YAML
  chmod 0644 "$tmp/config.yaml"
  mount_config=(-v "$tmp/config.yaml:/etc/sms-gateway/config.yaml:ro")

  podman run --rm --health-cmd none "${mount_config[@]}" "$image" --check-config /etc/sms-gateway/config.yaml >"$tmp/check.log" 2>&1 \
    || { cat "$tmp/check.log" >&2; fail "--check-config on the mounted config"; }
  check "--check-config /etc/sms-gateway/config.yaml on a mounted config: exit 0"

  serial_ctr=$run_id-serial
  containers+=("$serial_ctr")
  port=$(free_port)
  t0=$(now)
  start_container --init --name "$serial_ctr" -p "127.0.0.1:$port:502" -v "$pts:/dev/ttyUSB0" "${mount_config[@]}" \
    "${hardening[@]}" "$image"
  wait_for_modbus "$port" 255 30 || { podman logs "$serial_ctr" | tail -20 >&2; fail "config mounted: no answer on 502"; }
  for unit in 1 2 3; do
    wait_for_modbus "$port" "$unit" 10 1001 1 \
      || { podman logs "$serial_ctr" | tail -20 >&2; fail "servo unit $unit on the pty not online"; }
  done
  check "config mounted -> entrypoint runs it, on 0.0.0.0:502 (SMS_GATEWAY_LISTEN); servo units 1-3 online over the pty as /dev/ttyUSB0 (user sms through dialout) after $(elapsed "$t0") s"

  # A write goes through the container to the servo and is acknowledged; a live read sees it.
  # sts address 42 = goal position; mbpoll numbers from 1 without -0.
  mbpoll -m tcp -p "$port" -a 2 -0 -t 4 -r 42 -1 -o 1 127.0.0.1 1234 >"$tmp/write.log" 2>&1 \
    || { cat "$tmp/write.log" >&2; fail "FC06 write of goal position 1234 to unit 2"; }
  goal=$(mbpoll -m tcp -p "$port" -a 2 -0 -t 4 -r 42 -c 1 -1 -o 1 127.0.0.1 | awk '/^\[42\]:/ { print $2 }')
  [ "$goal" = 1234 ] || fail "unit 2 holding register 42 reads '$goal' after writing 1234"
  check "write goal position 1234 to unit 2 (FC06) acknowledged, live read (FC03) returns 1234"

  stop_and_check "$serial_ctr" "config mounted, with --init"
fi

# --- the systemd unit (no systemd runs here: checked offline) -------------------------------------
unit=$context/deploy/sms-gateway.service
if command -v systemd-analyze >/dev/null 2>&1 && [ -f "$unit" ]; then
  # verify insists that ExecStart exists: point it at the image's binary.
  sed "s#/usr/bin/sms-gateway#$tmp/sms-gateway#g" "$unit" >"$tmp/sms-gateway.service"
  # --man=no: the unit's Documentation= names the package's man pages, which are not installed on
  # the machine that builds the image.
  systemd-analyze verify --man=no "$tmp/sms-gateway.service" >"$tmp/verify.log" 2>&1 \
    || { cat "$tmp/verify.log" >&2; fail "systemd-analyze verify deploy/sms-gateway.service"; }
  [ ! -s "$tmp/verify.log" ] || { cat "$tmp/verify.log" >&2; fail "systemd-analyze verify: warnings"; }
  exposure=$(systemd-analyze security --offline=yes --no-pager "$tmp/sms-gateway.service" 2>&1 \
             | sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]* [A-Z]*\).*/\1/p')
  check "deploy/sms-gateway.service: systemd-analyze verify clean, security exposure ${exposure:-?} (offline)"
  unit_checked=yes
fi

# --- SMS_GATEWAY_* variables read by sms-gateway itself (config/env.h) ---------------------------
# JSON logs at debug level, the metrics endpoint, and an allow-list that admits the container's
# own loopback (the HEALTHCHECK) but not the host: podman's port forwarding shows the host as the
# bridge's address, and 192.0.2.0/24 is a documentation network nothing comes from.
env_ctr=$run_id-env
containers+=("$env_ctr")
port=$(free_port)
metrics_port=$(free_port)
start_container --init --name "$env_ctr" -p "127.0.0.1:$port:502" -p "127.0.0.1:$metrics_port:9102" \
  -e SMS_GATEWAY_LOG_FORMAT=json -e SMS_GATEWAY_LOG_LEVEL=debug -e SMS_GATEWAY_METRICS=0.0.0.0:9102 \
  -e SMS_GATEWAY_ALLOW=192.0.2.0/24,127.0.0.1 "${hardening[@]}" "$image"
deadline=$(( $(date +%s) + 30 ))
until curl -fs -o /dev/null "http://127.0.0.1:$metrics_port/healthz"; do
  [ "$(date +%s)" -lt "$deadline" ] || { podman logs "$env_ctr" | tail -20 >&2; fail "SMS_GATEWAY_METRICS: no /healthz 200 within 30 s"; }
  sleep 0.2
done
podman healthcheck run "$env_ctr" >/dev/null \
  || fail "SMS_GATEWAY_ALLOW=192.0.2.0/24,127.0.0.1: the HEALTHCHECK (from 127.0.0.1 inside) was refused"
if read_input_registers "$port" 255 0 1 >/dev/null; then
  fail "SMS_GATEWAY_ALLOW=192.0.2.0/24,127.0.0.1: a read from the host was answered"
fi
curl -fsS "http://127.0.0.1:$metrics_port/metrics" >"$tmp/metrics.txt" || fail "GET /metrics"
refused=$(awk '/^sms_gateway_tcp_connections_refused_total\{listener="plain",reason="allow"\}/ { print $2 }' "$tmp/metrics.txt")
[ "${refused:-0}" -ge 1 ] 2>/dev/null || fail "/metrics: refused{listener=\"plain\",reason=\"allow\"} = '${refused:-missing}' after a refused host read"
grep -q '^sms_gateway_build_info{version="'"$want_version"'"} 1' "$tmp/metrics.txt" || fail "/metrics: no sms_gateway_build_info for $want_version"
check "SMS_GATEWAY_METRICS=0.0.0.0:9102: /healthz 200, /metrics has build_info $want_version; SMS_GATEWAY_ALLOW=192.0.2.0/24,127.0.0.1: host refused (refused_total{listener=\"plain\",reason=\"allow\"} = $refused), HEALTHCHECK healthy"
command podman logs "$env_ctr" >"$tmp/env.log" 2>&1
non_json=$(grep -c -v '^{"ts":"[^"]*","level":"[a-z]*",.*}$' "$tmp/env.log" || true)
[ "$non_json" = 0 ] || { grep -v '^{"ts":' "$tmp/env.log" | head -5 >&2; fail "SMS_GATEWAY_LOG_FORMAT=json: $non_json log lines are not JSON objects"; }
grep -q '"level":"debug"' "$tmp/env.log" || fail "SMS_GATEWAY_LOG_LEVEL=debug: no debug record in $(wc -l <"$tmp/env.log") log lines"
grep -q 'from the environment:.*SMS_GATEWAY_METRICS' "$tmp/env.log" || fail "no log line naming the variables applied from the environment"
check "SMS_GATEWAY_LOG_FORMAT=json, SMS_GATEWAY_LOG_LEVEL=debug: $(wc -l <"$tmp/env.log") log lines, every one a JSON object, debug records present"
stop_and_check "$env_ctr" "JSON logs, metrics, allow-list"

# An invalid variable stops the gateway before it serves: exit status 2, the variable named.
set +e
command podman run --rm --health-cmd none -e SMS_GATEWAY_MAX_CONNECTIONS=0 "$image" >"$tmp/bad-env.log" 2>&1
code=$?
set -e
[ "$code" = 2 ] && grep -q 'SMS_GATEWAY_MAX_CONNECTIONS' "$tmp/bad-env.log" \
  || { cat "$tmp/bad-env.log" >&2; fail "SMS_GATEWAY_MAX_CONNECTIONS=0: exit status $code (want 2, naming the variable)"; }
check "SMS_GATEWAY_MAX_CONNECTIONS=0 refused: exit status 2, \"$(grep -m1 SMS_GATEWAY_MAX_CONNECTIONS "$tmp/bad-env.log" | cut -c1-90)...\""


echo
echo "container-test: passed in $(elapsed "$total_t0") s. Checked:"
printf '  %s\n' "${checks[@]}"
[ "$serial_checked" = yes ] || echo "NOT checked: the mounted config and the serial device (see above)"
[ "${unit_checked:-no}" = yes ] || echo "NOT checked: the systemd unit (no systemd-analyze)"
echo "Not checked here: a real USB adapter (--device), Docker itself, health checks on a timer"
echo "(podman runs them only on request without systemd), the systemd unit under a running systemd."
