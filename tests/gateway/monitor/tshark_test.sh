#!/usr/bin/env bash
# tshark_test.sh MONITOR_CAPTURE LUA: captures of real exchanges (monitor_capture: the gateway
# over the simulator on a pty, one goal-position write) opened with tshark (docs/MONITOR.md):
# - feetech and d55d buses through the packaged dissector (deploy/wireshark/sms_servo.lua): the
#   write is named WRITE, to ID 1, with a valid checksum, and the servo's answer says it answers
#   the WRITE;
# - a modbus-rtu bus through Wireshark's own Modbus RTU dissector, mapped by a user DLT (no Lua)
#   and by the Lua file: function code 6 to unit 1.
# Exit 77 (skipped) without tshark.
set -euo pipefail
capture=$1
lua=$2
command -v tshark >/dev/null || { echo "tshark not installed (scripts/install-deps.sh installs it): skipped"; exit 77; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export HOME=$work  # no personal Wireshark profile or plugins

fail() { echo "FAIL: $*" >&2; exit 1; }

for protocol in feetech d55d; do
  file=$work/$protocol.pcapng
  "$capture" "$protocol" "$file"
  requests=$(tshark -X "lua_script:$lua" -r "$file" -Y 'sms_servo.direction == "to servos"' \
             -T fields -e sms_servo.protocol -e sms_servo.id -e sms_servo.instruction_name -e sms_servo.checksum_ok 2>/dev/null)
  echo "$protocol requests:"; echo "$requests"
  grep -qP "^$protocol\t1\tWRITE\t(1|True)$" <<<"$requests" || fail "$protocol: no WRITE to ID 1 with a valid checksum"
  answers=$(tshark -X "lua_script:$lua" -r "$file" -Y 'sms_servo.direction == "from servos"' \
            -T fields -e sms_servo.id -e sms_servo.answer_to -e sms_servo.status 2>/dev/null)
  echo "$protocol answers:"; echo "$answers"
  grep -qP "^1\tWRITE\t0x0*0$" <<<"$answers" || fail "$protocol: no answer of ID 1 to the WRITE"
done

file=$work/modbus-rtu.pcapng
"$capture" modbus-rtu "$file"
by_dlt=$(tshark -o 'uat:user_dlts:"User 1 (DLT=148)","mbrtu","0","","0",""' -r "$file" \
         -T fields -e mbrtu.unit_id -e modbus.func_code 2>/dev/null)
echo "modbus-rtu by user DLT:"; echo "$by_dlt"
grep -qP "^1\t6$" <<<"$by_dlt" || fail "modbus-rtu: Wireshark's Modbus RTU dissector found no function 6 to unit 1"
by_lua=$(tshark -X "lua_script:$lua" -r "$file" -T fields -e mbrtu.unit_id -e modbus.func_code 2>/dev/null)
grep -qP "^1\t6$" <<<"$by_lua" || fail "modbus-rtu: the Lua file does not hand link type 148 to mbrtu"
echo "ok"
