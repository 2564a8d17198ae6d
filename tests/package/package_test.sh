#!/usr/bin/env bash
# The Debian package in a light form (README "Install"): CPack builds it from this build tree,
# its metadata and files are checked, it is unpacked into a scratch root whose sms-gateway must
# answer --version and --check-config, its postinst runs against stand-in user tools that
# record what it asks for, and apt-get resolves its dependencies in a simulation (the real
# install, `apt install ./sms-gateway_*.deb`, changes the machine's users: scripts/package.sh
# --install does it on demand).
#
#   package_test.sh CPACK_COMMAND BUILD_DIR SOURCE_DIR
set -euo pipefail
cpack=$1 build=$2 source=$3
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT

fail() { echo "package_test: $*" >&2; exit 1; }

"$cpack" -G DEB --config "$build/CPackConfig.cmake" -B "$scratch/out" >"$scratch/cpack.log" 2>&1 ||
  { cat "$scratch/cpack.log"; fail "cpack could not build the package"; }
deb=$(ls "$scratch"/out/sms-gateway_*_*.deb 2>/dev/null | head -1)
[ -n "$deb" ] || fail "no sms-gateway_*.deb in $scratch/out"

info=$(dpkg-deb --info "$deb")
grep -q '^ Package: sms-gateway$' <<<"$info" || fail "package name: $info"
grep -q '^ Depends:.*adduser' <<<"$info" || fail "no Depends on adduser (postinst uses it)"
grep -q '^ Depends:.*libmodbus5' <<<"$info" || fail "no library Depends (dpkg-shlibdeps did not run)"
for script in postinst prerm postrm; do grep -q " $script " <<<"$info" || fail "no $script in the control archive"; done

contents=$(dpkg-deb --contents "$deb" | awk '{print $6}')
for path in ./usr/bin/sms-gateway ./usr/bin/sms-sim ./usr/lib/systemd/system/sms-gateway.service \
            ./usr/share/doc/sms-gateway/README.md ./usr/share/doc/sms-gateway/examples/mixed.yaml; do
  grep -qx "$path" <<<"$contents" || fail "$path is not in the package"
done

root="$scratch/root"
dpkg-deb -x "$deb" "$root"
version=$("$root/usr/bin/sms-gateway" --version)
grep -q '^sms-gateway [0-9]' <<<"$version" || fail "sms-gateway --version said: $version"
for example in "$root"/usr/share/doc/sms-gateway/examples/*.yaml; do
  "$root/usr/bin/sms-gateway" --check-config "$example" >/dev/null || fail "--check-config $(basename "$example") failed"
done
unit="$root/usr/lib/systemd/system/sms-gateway.service"
grep -q '^ExecStart=/usr/bin/sms-gateway --config /etc/sms-gateway/config.yaml$' "$unit" ||
  fail "the unit does not start /usr/bin/sms-gateway: $(grep Exec "$unit")"
grep -q '^SupplementaryGroups=dialout$' "$unit" || fail "the unit lost its dialout group"

# postinst on a machine without the user: it creates group and user, and puts the user in dialout.
control="$scratch/control"
dpkg-deb -e "$deb" "$control"
stand_ins="$scratch/bin"
mkdir -p "$stand_ins"
for tool in addgroup adduser systemctl install rmdir; do
  printf '#!/bin/sh\necho "%s $*" >>"%s"\n' "$tool" "$scratch/calls" >"$stand_ins/$tool"
done
printf '#!/bin/sh\nexit 2\n' >"$stand_ins/getent"  # nothing known yet
chmod +x "$stand_ins"/*
PATH="$stand_ins:$PATH" sh "$control/postinst" configure || fail "postinst configure failed"
calls=$(cat "$scratch/calls")
grep -q '^addgroup --system --quiet sms$' <<<"$calls" || fail "postinst did not create the group: $calls"
grep -q '^adduser --system --quiet --ingroup sms .* sms$' <<<"$calls" || fail "postinst did not create the user: $calls"
grep -q '^adduser --quiet sms dialout$' <<<"$calls" || fail "postinst did not add sms to dialout: $calls"
grep -q '^install -d -m 0755 /etc/sms-gateway$' <<<"$calls" || fail "postinst did not make /etc/sms-gateway: $calls"
for script in prerm postrm; do sh -n "$control/$script" || fail "$script is not valid sh"; done

# apt on this Debian 12 machine resolves every Depends (a shlibs name no package provides would
# make `apt install ./sms-gateway_*.deb` fail on the box); a simulation changes nothing.
if command -v apt-get >/dev/null; then
  apt-get install --simulate "$deb" >"$scratch/apt.log" 2>&1 ||
    { cat "$scratch/apt.log"; fail "apt-get cannot install the package (dependencies)"; }
  grep -q '^Inst sms-gateway ' "$scratch/apt.log" || fail "apt-get would not install it: $(cat "$scratch/apt.log")"
fi

echo "package_test: $(basename "$deb") ok ($(du -k "$deb" | cut -f1) KiB)"
