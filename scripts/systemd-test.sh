#!/usr/bin/env bash
# The Debian package under a real systemd (on demand; root; a few minutes). A Debian 12 root made
# by debootstrap (once, kept in SMS_SYSTEMD_DIR, default /var/tmp/sms-systemd-test) is booted with
# systemd-nspawn; at boot a one-shot unit in it runs the checks below against the package and
# powers the container off. Each check prints "ok:" or "FAIL:"; the exit status is 0 only when
# every check passed. Checked (docs/INSTALL.md "systemd"):
#   - a login user named _sms-gateway makes the installation fail, with the message;
#   - installing enables and starts neither unit; the account _sms-gateway is a system account
#     (nologin, in dialout) and both units run as it; systemd-analyze verify of both units;
#   - the installed README is the installed product's, documents over 4 KiB are compressed, the
#     manual pages render with `man --warnings` (80 and 120 columns) without a message;
#   - started without a config, and with a bad one: the unit ends `failed` with NRestarts=0 and
#     the gateway's message in the journal (no restart loop);
#   - the shipped simulated.yaml with sms-sim.service (both enabled): active, Modbus answers,
#     servos 1 and 6 included; a restart of the gateway while sms-sim holds the pty answers again;
#   - an upgrade restarts the running service (a new main PID, still active, servo 1 answers);
#   - purge leaves no enable link and no /var/lib/sms-gateway; a reinstall is not enabled;
#   - what an earlier package's `sms` account owned (config, state) becomes _sms-gateway's (the
#     gateway runs on it), and the sms account stays.
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
prop() { systemctl show -p "$1" --value "${2:-sms-gateway.service}"; }
wait_state() {  # wait_state STATE SECONDS [UNIT]
  for _ in $(seq 1 $(( $2 * 10 ))); do [ "$(prop ActiveState "${3:-sms-gateway.service}")" = "$1" ] && return 0; sleep 0.1; done; return 1
}
retry() {  # retry SECONDS COMMAND...: until it succeeds
  local end=$((SECONDS + $1)); shift
  until "$@" >/dev/null 2>&1; do [ "$SECONDS" -lt "$end" ] || return 1; sleep 0.5; done
}
servo_answers() { mbpoll -m tcp -p 5020 -a "$1" -t 3 -r 57 -c 15 -1 127.0.0.1 | grep -q '^\[57\]:'; }
gateway_answers() { mbpoll -m tcp -p 5020 -a 255 -t 3 -r 1 -c 3 -1 127.0.0.1 | grep -q '^\[1\]:'; }
doc=/usr/share/doc/sms-gateway

# A login user that happens to have the package's account name: the installation stops, and says why.
useradd --create-home --uid 1500 --shell /bin/bash _sms-gateway
apt-get install -y -q man-db /debs/current.deb >/results/apt-refused.log 2>&1
check "a login user named _sms-gateway: installing fails" \
  bash -c '! dpkg-query -W -f="\${Status}" sms-gateway | grep -q "install ok installed"'
check "a login user named _sms-gateway: the message names the account and uid" \
  grep -q 'the account _sms-gateway exists with uid 1500, which is not a system account' /results/apt-refused.log
check "a login user named _sms-gateway: the service is not started" test "$(prop ActiveState)" != active
userdel --remove _sms-gateway 2>/dev/null
dpkg --configure -a >/results/apt-install.log 2>&1
apt-get install -y -q man-db /debs/current.deb >>/results/apt-install.log 2>&1
check "the package installs (apt resolves its dependencies)" \
  bash -c 'dpkg-query -W -f="\${Status}" sms-gateway | grep -q "install ok installed"'
for unit in sms-gateway.service sms-sim.service; do
  check "installing does not enable $unit" test "$(systemctl is-enabled $unit)" = disabled
  check "installing does not start $unit" test "$(prop ActiveState $unit)" = inactive
done
uid=$(getent passwd _sms-gateway | cut -d: -f3)
shell=$(getent passwd _sms-gateway | cut -d: -f7)
check "the account _sms-gateway is a system account (uid $uid < 1000, shell $shell)" \
  bash -c "[ -n '$uid' ] && [ '$uid' -gt 0 ] && [ '$uid' -lt 1000 ] && [ '$shell' = /usr/sbin/nologin ]"
check "the account's group is _sms-gateway, and it is in dialout" \
  bash -c 'test "$(id -gn _sms-gateway)" = _sms-gateway && id -Gn _sms-gateway | grep -qw dialout'
check "the units run as _sms-gateway" \
  bash -c 'test "$(systemctl show -p User --value sms-gateway)" = _sms-gateway && test "$(systemctl show -p User --value sms-sim)" = _sms-gateway'
check "the console's key is 0640 root:_sms-gateway" \
  test "$(stat -c '%a %U:%G' /etc/sms-gateway/console/console.key)" = "640 root:_sms-gateway"
check "systemd-analyze verify of both units says nothing" \
  bash -c 'out=$(systemd-analyze verify /lib/systemd/system/sms-gateway.service /lib/systemd/system/sms-sim.service 2>&1); echo "$out"; [ -z "$out" ]'
check "sms-gateway is ordered after sms-sim" bash -c 'systemctl show -p Before --value sms-sim | grep -qw sms-gateway.service'

# The installed documents: the README is the installed product's; the Markdown documents are not
# compressed (their links name one another: debian/rules), the other documents over 4 KiB are.
check "README.md describes the installed package (config path, sms-sim, no ./scripts/)" \
  bash -c "grep -q /etc/sms-gateway/config.yaml $doc/README.md && grep -q 'systemctl enable --now sms-sim sms-gateway' $doc/README.md && ! grep -q 'scripts/' $doc/README.md"
check "the Markdown documents are not compressed (compressed: $(find $doc -name '*.md.gz' | tr '\n' ' '))" \
  bash -c "test -f $doc/docs/INSTALL.md && test -z \"\$(find $doc -name '*.md.gz')\""
check "other documents over 4 KiB are compressed (none left: $(find $doc -type f -size +4k ! -name '*.gz' ! -name '*.md' ! -name copyright ! -path '*/examples/*' ! -name '*.png' | tr '\n' ' '))" \
  bash -c "test -z \"\$(find $doc -type f -size +4k ! -name '*.gz' ! -name '*.md' ! -name copyright ! -path '*/examples/*' ! -name '*.png')\""
check "the examples are not compressed" test -f $doc/examples/simulated.yaml
for page in man1/sms-gateway.1.gz man1/sms-sim.1.gz man5/sms-gateway.yaml.5.gz; do
  for width in 80 120; do
    check "man --warnings $page at $width columns: no message" bash -c \
      "out=\$(LC_ALL=C.UTF-8 MANWIDTH=$width man --warnings -E UTF-8 -l -Tutf8 -Z /usr/share/man/$page 2>&1 >/dev/null); echo \"\$out\" | head -5; [ -z \"\$out\" ]"
  done
done

# No configuration: the package leaves /etc/sms-gateway empty.
systemctl start sms-gateway.service
wait_state failed 10; sleep 5   # RestartSec=2s: a restart loop would show by now
check "no config: the unit is failed" test "$(prop ActiveState)" = failed
check "no config: NRestarts=0 (got $(prop NRestarts))" test "$(prop NRestarts)" = 0
check "no config: exit status 2" test "$(prop ExecMainStatus)" = 2
check "no config: the journal says which file" bash -c 'journalctl -u sms-gateway --no-pager | grep -q "/etc/sms-gateway/config.yaml"'

# README "Run it on a bus": an example copied into place passes --check-config.
check "the README's example path: examples/mixed.yaml passes --check-config" \
  bash -c 'install -m 0640 -o root -g _sms-gateway /usr/share/doc/sms-gateway/examples/mixed.yaml /etc/sms-gateway/config.yaml &&
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

# README "Try it without hardware": the shipped simulated.yaml with sms-sim.service, both units enabled.
install -m 0640 -o root -g _sms-gateway $doc/examples/simulated.yaml /etc/sms-gateway/config.yaml
systemctl reset-failed sms-gateway.service
systemctl enable --now sms-sim sms-gateway >/dev/null 2>&1
wait_state active 10 sms-sim.service; wait_state active 10
check "simulated example: sms-sim is active, as _sms-gateway, its link /run/sms-sim/ttySIM0 there" \
  bash -c 'systemctl is-active --quiet sms-sim && test -e /run/sms-sim/ttySIM0 &&
           test "$(ps -o user= -p "$(systemctl show -p MainPID --value sms-sim)")" = _sms-gateway'
check "simulated example: sms-gateway is active" test "$(prop ActiveState)" = active
check "simulated example: Modbus answers (gateway unit 255, version)" retry 15 gateway_answers
check "simulated example: servo 1's feedback through the gateway" retry 15 servo_answers 1
check "simulated example: servo 6's feedback through the gateway" retry 15 servo_answers 6
check "systemctl reload (SIGHUP) keeps it running" bash -c 'systemctl reload sms-gateway && sleep 1 && systemctl is-active --quiet sms-gateway'
check "StateDirectory: /var/lib/sms-gateway exists, the account's" \
  test "$(stat -c %U /var/lib/sms-gateway 2>/dev/null)" = _sms-gateway

# A restart reopens a line another process holds: sms-sim keeps the pty, the gateway opens it again.
sim_pid=$(prop MainPID sms-sim.service)
gw_pid=$(prop MainPID)
systemctl restart sms-gateway
wait_state active 10
check "restart with sms-sim holding the pty: a new gateway (main PID $gw_pid -> $(prop MainPID)), the same sms-sim" \
  test "$(prop MainPID)" != "$gw_pid" -a "$(prop MainPID sms-sim.service)" = "$sim_pid"
check "restart with sms-sim holding the pty: servo 1 answers again" retry 15 servo_answers 1

# An upgrade restarts the running services.
pid_before=$(prop MainPID)
apt-get install -y -q /debs/upgrade.deb >/results/apt-upgrade.log 2>&1
wait_state active 10; sleep 1
pid_after=$(prop MainPID)
check "upgrade: the running service was restarted (main PID $pid_before -> $pid_after)" \
  test "$pid_after" != "$pid_before" -a "$pid_after" != 0
check "upgrade: active afterwards" test "$(prop ActiveState)" = active
check "upgrade: the new binary runs" bash -c "test \"\$(readlink /proc/$pid_after/exe)\" = /usr/bin/sms-gateway"
check "upgrade: servo 1 answers" retry 15 servo_answers 1

# Purge: no enable link, no state; a reinstall is not enabled.
apt-get purge -y -q sms-gateway >/results/apt-purge.log 2>&1
check "purge: no enable link left" bash -c '! ls /etc/systemd/system/*.wants/sms-gateway.service /etc/systemd/system/*.wants/sms-sim.service 2>/dev/null | grep -q .'
check "purge: /var/lib/sms-gateway removed" test ! -e /var/lib/sms-gateway
check "purge: neither program is running" bash -c '! pgrep -x sms-gateway && ! pgrep -x sms-sim'
apt-get install -y -q /debs/current.deb >>/results/apt-install.log 2>&1
check "reinstall after purge: not enabled" test "$(systemctl is-enabled sms-gateway.service)" = disabled
check "reinstall after purge: not started" test "$(prop ActiveState)" != active

# What an earlier package that ran the service as `sms` leaves: a config and state of sms's.
# Configuring again hands the config to _sms-gateway, the next start the state (StateDirectory=);
# the sms account stays.
adduser --system --group --quiet --no-create-home --home /nonexistent sms
chown root:sms /etc/sms-gateway/config.yaml
install -d -o sms -g sms -m 0750 /var/lib/sms-gateway
install -o sms -g sms -m 0600 /dev/null /var/lib/sms-gateway/left-by-sms
apt-get install -y -q --reinstall /debs/current.deb >/results/apt-reinstall.log 2>&1
check "from sms: config.yaml is root:_sms-gateway" test "$(stat -c %U:%G /etc/sms-gateway/config.yaml)" = root:_sms-gateway
systemctl start sms-sim sms-gateway
wait_state active 10
check "from sms: the gateway runs on that config, servo 1 answers" retry 15 servo_answers 1
check "from sms: the state is _sms-gateway's after the start" \
  test "$(stat -c %U:%G /var/lib/sms-gateway /var/lib/sms-gateway/left-by-sms | sort -u)" = _sms-gateway:_sms-gateway
check "from sms: the sms account is still there" getent passwd sms

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
