#!/usr/bin/env bash
# The Debian package under a real systemd (on demand; root; a few minutes). A Debian 12 root made
# by debootstrap (once, kept in SMS_SYSTEMD_DIR, default /var/tmp/sms-systemd-test) is booted with
# systemd-nspawn; at boot a one-shot unit in it runs the checks below against the package and
# powers the container off. Each check prints "ok:" or "FAIL:"; the exit status is 0 only when
# every check passed. Checked (docs/INSTALL.md "systemd"):
#   - installing does not enable or start the service;
#   - started without a config, and with a bad one: the unit ends `failed` with NRestarts=0 and
#     the gateway's message in the journal (no restart loop);
#   - with a config on a simulated bus (sms-sim on a pty, as user sms): active, Modbus answers;
#   - an upgrade restarts the running service (a new main PID, still active);
#   - purge leaves no enable link and no /var/lib/sms-gateway; a reinstall is not enabled.
#
#   scripts/systemd-test.sh [DEB]      # default: the newest build-deb/sms-gateway_*.deb (scripts/package.sh)
set -euo pipefail
cd "$(dirname "$0")/.."
[ "$(id -u)" -eq 0 ] || { echo "systemd-test: needs root (debootstrap, systemd-nspawn)" >&2; exit 1; }
deb=${1:-$(ls -t build-deb/sms-gateway_*_*.deb 2>/dev/null | grep -v dbgsym | head -1 || true)}
[ -n "$deb" ] && [ -f "$deb" ] || { echo "systemd-test: no package: run scripts/package.sh first, or name the .deb" >&2; exit 1; }

work=${SMS_SYSTEMD_DIR:-/var/tmp/sms-systemd-test}
for p in debootstrap systemd-container; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" ||
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$p" >/dev/null
done
mirror=$(awk '/^URIs:/ { print $2; exit }' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
mirror=${mirror:-http://deb.debian.org/debian}
if [ ! -d "$work/root" ]; then
  echo "systemd-test: making a Debian 12 root with systemd in $work/root (once)" >&2
  mkdir -p "$work"
  debootstrap --variant=minbase --include=systemd,systemd-sysv,dbus,mbpoll,man-db,ca-certificates \
    bookworm "$work/root.new" "$mirror" >"$work/debootstrap.log" 2>&1 ||
    { tail -20 "$work/debootstrap.log" >&2; exit 1; }
  mv "$work/root.new" "$work/root"
fi

# Each run starts from a copy of the clean root.
run=$work/run
rm -rf "$run" && cp -a "$work/root" "$run"
mkdir -p "$run/debs" "$run/results"
cp "$deb" "$run/debs/current.deb"
# The "upgrade": the same package with a higher version.
repack=$(mktemp -d)
trap 'rm -rf "$repack"' EXIT
dpkg-deb -R "$deb" "$repack/pkg"
sed -i 's/^Version: \(.*\)$/Version: \1+systemdtest1/' "$repack/pkg/DEBIAN/control"
dpkg-deb -Zgzip -z1 -b "$repack/pkg" "$run/debs/upgrade.deb" >/dev/null

cat >"$run/usr/local/sbin/sms-package-checks" <<'CHECKS'
#!/bin/bash
# Runs inside the container under systemd; results in /results/log.
exec >/results/log 2>&1
set -u
export DEBIAN_FRONTEND=noninteractive
failed=0
check() { local what=$1; shift; if "$@"; then echo "ok: $what"; else echo "FAIL: $what"; failed=1; fi; }
prop() { systemctl show -p "$1" --value sms-gateway.service; }
wait_state() {  # wait_state STATE SECONDS
  for _ in $(seq 1 $(( $2 * 10 ))); do [ "$(prop ActiveState)" = "$1" ] && return 0; sleep 0.1; done; return 1
}

apt-get install -y -q man-db /debs/current.deb >/results/apt-install.log 2>&1
check "the package installs (apt resolves its dependencies)" dpkg-query -W sms-gateway
check "installing does not enable the service" test "$(systemctl is-enabled sms-gateway.service)" = disabled
check "installing does not start the service" test "$(prop ActiveState)" = inactive
check "man sms-gateway, man sms-sim, man 5 sms-gateway.yaml" \
  bash -c 'man -w sms-gateway && man -w sms-sim && man -w 5 sms-gateway.yaml' 

# No configuration: the package leaves /etc/sms-gateway empty.
systemctl start sms-gateway.service
wait_state failed 10; sleep 5   # RestartSec=2s: a restart loop would show by now
check "no config: the unit is failed" test "$(prop ActiveState)" = failed
check "no config: NRestarts=0 (got $(prop NRestarts))" test "$(prop NRestarts)" = 0
check "no config: exit status 2" test "$(prop ExecMainStatus)" = 2
check "no config: the journal says which file" bash -c 'journalctl -u sms-gateway --no-pager | grep -q "/etc/sms-gateway/config.yaml"'

# README "Install and deploy": an example copied into place passes --check-config.
check "the README's example path: examples/mixed.yaml passes --check-config" \
  bash -c 'install -m 0640 -o root -g sms /usr/share/doc/sms-gateway/examples/mixed.yaml /etc/sms-gateway/config.yaml &&
           sms-gateway --check-config /etc/sms-gateway/config.yaml'
# A bad configuration: the message with file:line:column.
systemctl reset-failed sms-gateway.service
printf 'buses:\n  - {name: arm, device: /dev/ttyUSB0, protocol: feetech, baud: 1234}\nservos: []\n' >/etc/sms-gateway/config.yaml
check "bad config: --check-config exits 2" bash -c 'sms-gateway --check-config /etc/sms-gateway/config.yaml; test $? = 2'
systemctl start sms-gateway.service
wait_state failed 10; sleep 5
check "bad config: the unit is failed" test "$(prop ActiveState)" = failed
check "bad config: NRestarts=0 (got $(prop NRestarts))" test "$(prop NRestarts)" = 0
check "bad config: the journal has config.yaml:line:column" bash -c 'journalctl -u sms-gateway --no-pager | grep -q "config.yaml:2:[0-9]*:"'
journalctl -u sms-gateway --no-pager | tail -3

# A good configuration on a simulated bus: sms-sim on a pty, as user sms like the gateway.
systemd-run --unit=sms-sim --uid=sms --gid=sms -p RuntimeDirectory=sms-sim \
  /usr/bin/sms-sim --ids 1-3 --link /run/sms-sim/ttySIM0 >/dev/null
for _ in $(seq 1 50); do [ -e /run/sms-sim/ttySIM0 ] && break; sleep 0.1; done
cat >/etc/sms-gateway/config.yaml <<'YAML'
modbus_tcp: {listen: "127.0.0.1:5020"}
buses:
  - {name: sim, device: /run/sms-sim/ttySIM0, protocol: feetech, baud: 1000000}
servos:
  - {bus: sim, id: 1, table: sts}
  - {bus: sim, id: 2, table: sts}
  - {bus: sim, id: 3, table: sts}
YAML
systemctl reset-failed sms-gateway.service
systemctl enable --now sms-gateway.service
wait_state active 10; sleep 2
check "good config: the unit is active" test "$(prop ActiveState)" = active
check "good config: Modbus answers (gateway unit 255, version)" \
  bash -c 'mbpoll -m tcp -p 5020 -a 255 -t 3 -r 1 -c 3 -1 127.0.0.1 | grep -q "^\[1\]:"'
check "good config: servo 1 answers through the gateway" \
  bash -c 'mbpoll -m tcp -p 5020 -a 1 -t 4 -r 43 -1 127.0.0.1 | grep -q "^\[43\]:"'
check "systemctl reload (SIGHUP) keeps it running" bash -c 'systemctl reload sms-gateway && sleep 1 && systemctl is-active --quiet sms-gateway'
check "StateDirectory: /var/lib/sms-gateway exists" test -d /var/lib/sms-gateway

# An upgrade restarts the running service.
pid_before=$(prop MainPID)
apt-get install -y -q /debs/upgrade.deb >/results/apt-upgrade.log 2>&1
wait_state active 10; sleep 1
pid_after=$(prop MainPID)
check "upgrade: the running service was restarted (main PID $pid_before -> $pid_after)" \
  test "$pid_after" != "$pid_before" -a "$pid_after" != 0
check "upgrade: active afterwards" test "$(prop ActiveState)" = active
check "upgrade: the new binary runs" bash -c "test \"\$(readlink /proc/$pid_after/exe)\" = /usr/bin/sms-gateway"

# Purge: no enable link, no state; a reinstall is not enabled.
apt-get purge -y -q sms-gateway >/results/apt-purge.log 2>&1
check "purge: no enable link left" bash -c '! ls /etc/systemd/system/*.wants/sms-gateway.service 2>/dev/null | grep -q .'
check "purge: /var/lib/sms-gateway removed" test ! -e /var/lib/sms-gateway
check "purge: the service is not running" bash -c '! pgrep -x sms-gateway'
apt-get install -y -q /debs/current.deb >>/results/apt-install.log 2>&1
check "reinstall after purge: not enabled" test "$(systemctl is-enabled sms-gateway.service)" = disabled
check "reinstall after purge: not started" test "$(prop ActiveState)" != active

echo "result: $([ "$failed" = 0 ] && echo PASS || echo FAIL)"
systemctl poweroff
CHECKS
chmod +x "$run/usr/local/sbin/sms-package-checks"
cat >"$run/etc/systemd/system/sms-package-checks.service" <<'UNIT'
[Unit]
Description=sms-gateway package checks (scripts/systemd-test.sh)
After=multi-user.target network-online.target
[Service]
Type=oneshot
ExecStart=/usr/local/sbin/sms-package-checks
[Install]
WantedBy=multi-user.target
UNIT
ln -sf /etc/systemd/system/sms-package-checks.service "$run/etc/systemd/system/multi-user.target.wants/"
cp /etc/resolv.conf "$run/etc/resolv.conf" 2>/dev/null || true
cp /etc/apt/sources.list.d/debian.sources "$run/etc/apt/sources.list.d/" 2>/dev/null || true

echo "systemd-test: booting $run with systemd-nspawn ($(basename "$deb"))" >&2
# --register=no --keep-unit: no machined or systemd needed on the host (a build container).
timeout 600 systemd-nspawn --quiet --boot --register=no --keep-unit --directory="$run" --machine=sms-systemd-test \
  >"$work/nspawn.log" 2>&1 || true
if [ ! -s "$run/results/log" ]; then
  tail -30 "$work/nspawn.log" >&2
  echo "systemd-test: the container produced no results (log above)" >&2
  exit 1
fi
grep -E '^(ok|FAIL|result):' "$run/results/log"
grep -q '^result: PASS$' "$run/results/log"
