#!/usr/bin/env bash
# Command-line errors end with exit status 2, as README "Command line" and the man pages say
# (CLI11's own codes — 105, 109, 114 ... — are not a documented interface); --help and
# --version end with 0, unless help is asked of a command or option that does not exist.
# systemd's RestartPreventExitStatus=2 relies on it.
#
#   usage_exit_status_test.sh BIN_DIR
set -uo pipefail
bin=$1
failures=0
expect() {
  local want=$1; shift
  "$@" >/dev/null 2>&1 </dev/null
  local got=$?
  if [ "$got" -ne "$want" ]; then
    echo "usage_exit_status: '$*' exited $got, expected $want" >&2
    failures=$((failures + 1))
  fi
}
gw="$bin/sms-gateway" sim="$bin/sms-sim"
expect 0 "$gw" --help
expect 0 "$gw" --version
expect 0 "$gw" scan --help
expect 2 "$gw" --bogus
expect 2 "$gw" --listen
expect 2 "$gw" --log-level loud
expect 2 "$gw" --check-config
expect 2 "$gw" --config a.yaml --simulate
expect 2 "$gw"
expect 2 "$gw" scan --bogus
expect 2 "$gw" set-id --device /dev/null
# A command that does not exist, also when help is asked of it: said, with status 2, not the
# general help with 0.
expect 2 "$gw" no-such-command
expect 2 "$gw" no-such-command --help
expect 2 "$gw" --no-such-option --help
says() {
  local text=$1; shift
  local out
  out=$("$@" 2>&1 </dev/null)
  if ! grep -qF -- "$text" <<<"$out"; then
    echo "usage_exit_status: '$*' does not say '$text': $out" >&2
    failures=$((failures + 1))
  fi
}
says "no command no-such-command; the commands are forward, scan, set-id" "$gw" no-such-command --help
says "no option --no-such-option" "$gw" --no-such-option --help
expect 0 "$sim" --help
expect 2 "$sim" --bogus
expect 2 "$sim" --baud
[ "$failures" -eq 0 ] && echo "usage_exit_status: ok"
exit $((failures > 0))
