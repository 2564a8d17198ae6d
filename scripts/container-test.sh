#!/usr/bin/env bash
# Container check, separate from scripts/test.sh (it needs root and about a minute):
# builds docker/Dockerfile with podman (daemonless, no registry needed) and runs the image the
# way the README says, checking each claim the README makes about it. Prints what it checked.
#
#   ./scripts/container-test.sh            # build context = the working tree
#   ./scripts/container-test.sh --head     # build context = the committed HEAD (git archive)
#
# Exits 0 with "skipped: podman not available" when podman is missing.
# Environment: SMS_CONTAINER_DIR (default /tmp/ctr) holds podman's storage and configuration
# unless CONTAINERS_CONF / CONTAINERS_STORAGE_CONF are set (see ../shared/CONTAINERS.md).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD

if ! command -v podman >/dev/null 2>&1; then
  echo "container-test: skipped: podman not available (apt-get install podman buildah debootstrap runc)"
  exit 0
fi
if ! command -v mbpoll >/dev/null 2>&1; then
  echo "container-test: mbpoll is needed for the Modbus reads from the host: run scripts/install-deps.sh" >&2
  exit 1
fi

context_mode=worktree
for arg in "$@"; do
  case "$arg" in
    --head) context_mode="head" ;;
    *) echo "usage: $0 [--head]" >&2; exit 2 ;;
  esac
done

image=localhost/sms-gateway:container-test
run_id=sms-ctr-test-$$
containers=()
sim_pid=
tmp=$(mktemp -d)
cleanup() {
  local c
  for c in "${containers[@]}"; do podman rm -f -t 0 "$c" >/dev/null 2>&1 || true; done
  if [ -n "$sim_pid" ]; then kill "$sim_pid" 2>/dev/null || true; fi
  rm -rf "$tmp"
}
trap cleanup EXIT

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

# --- podman environment (the recipe of ../shared/CONTAINERS.md) ------------------------------
work=${SMS_CONTAINER_DIR:-/tmp/ctr}
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
  rm -rf "$rootfs"
  debootstrap --variant=minbase bookworm "$rootfs" "${mirror:-http://deb.debian.org/debian}" >"$tmp/debootstrap.log" 2>&1 \
    || { tail -20 "$tmp/debootstrap.log" >&2; fail "debootstrap of the base image"; }
  chroot "$rootfs" apt-get clean
  if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    cp /etc/apt/sources.list.d/debian.sources "$rootfs/etc/apt/sources.list.d/" && rm -f "$rootfs/etc/apt/sources.list"
  fi
  tar -C "$rootfs" -c . | podman import --change 'CMD ["bash"]' - docker.io/library/debian:bookworm >/dev/null
  rm -rf "$rootfs"
  check "base image debian:bookworm made with debootstrap in $(elapsed "$t0") s"
fi
podman image exists docker.io/library/debian:bookworm-slim \
  || podman tag docker.io/library/debian:bookworm docker.io/library/debian:bookworm-slim

# --- build -------------------------------------------------------------------------------------
context=$repo
if [ "$context_mode" = head ]; then
  context=$tmp/context
  mkdir -p "$context"
  git -C "$repo" archive HEAD | tar -x -C "$context"
fi
t0=$(now)
podman build --format docker -f "$context/docker/Dockerfile" -t "$image" "$context" >"$tmp/build.log" 2>&1 \
  || { tail -40 "$tmp/build.log" >&2; fail "podman build (context: $context_mode)"; }
check "image built from the $context_mode in $(elapsed "$t0") s ($(podman image inspect --format '{{.Size}}' "$image" | awk '{ printf "%.0f MB", $1 / 1e6 }'))"

# --- what the image declares and contains ------------------------------------------------------
[ "$(podman image inspect --format '{{.Config.User}}' "$image")" = "sms:sms" ] || fail "image USER is not sms:sms"
podman image inspect --format '{{json .Config.ExposedPorts}}' "$image" | grep -q '"502/tcp"' || fail "image does not EXPOSE 502"
podman image inspect --format '{{json .Config.Healthcheck}}' "$image" | grep -q mbpoll || fail "image has no HEALTHCHECK (built without --format docker?)"
check "image metadata: USER sms:sms, EXPOSE 502/tcp, HEALTHCHECK kept"

ids=$(podman run --rm --entrypoint id "$image")
case "$ids" in *"uid=502(sms)"*"dialout"*) ;; *) fail "container user: $ids";; esac
check "container runs as $ids"

podman run --rm --entrypoint dpkg-query "$image" -W -f '${Package}\n' >"$tmp/packages"
if grep -E -- '-dev$|^(g\+\+|gcc|cpp|cmake|ninja-build)(-[0-9]+)?$' "$tmp/packages" >"$tmp/build-packages"; then
  fail "runtime image holds build packages: $(tr '\n' ' ' <"$tmp/build-packages")"
fi
check "runtime image has no compiler, cmake or -dev package ($(wc -l <"$tmp/packages") packages)"

want_version=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' "$context/CMakeLists.txt")
got_version=$(podman run --rm "$image" --version)
grep -qF "$want_version" <<<"$got_version" || fail "'--version' says '$got_version', CMakeLists.txt says $want_version"
check "entrypoint passes options to sms-gateway: --version -> $got_version"

# --- the simulated bus, hardened as in docker-compose.yml ----------------------------------------
hardening=(--read-only --tmpfs /tmp --cap-drop ALL --security-opt no-new-privileges
           --sysctl net.ipv4.ip_unprivileged_port_start=0)
port=$(free_port)
sim_ctr=$run_id-sim
containers+=("$sim_ctr")
t0=$(now)
podman run -d --init --name "$sim_ctr" -p "127.0.0.1:$port:502" "${hardening[@]}" "$image" >/dev/null
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
podman run -d --name "$off_ctr" -p "127.0.0.1:$other_port:5020" "$image" --simulate --listen 0.0.0.0:5020 >/dev/null
wait_for_modbus "$other_port" 255 30 || { podman logs "$off_ctr" | tail -20 >&2; fail "gateway on 5020 did not answer"; }
if podman healthcheck run "$off_ctr" >/dev/null 2>&1; then
  fail "healthcheck says healthy although nothing answers on port 502"
fi
check "healthcheck reports unhealthy when the gateway serves but not on 502"

stop_and_check "$sim_ctr" "with --init"
stop_and_check "$off_ctr" "without --init (sms-gateway is PID 1)"

echo
echo "container-test: passed in $(elapsed "$total_t0") s. Checked:"
printf '  %s\n' "${checks[@]}"
echo "Not checked here: a real USB adapter (--device), Docker itself, health checks on a timer"
echo "(podman runs them only on request without systemd)."
