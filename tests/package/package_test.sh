#!/usr/bin/env bash
# The Debian package in a light form (docs/INSTALL.md "The Debian package"): debhelper makes it
# from debian/ exactly as `dpkg-buildpackage` does, except that the programs come from this build
# tree (SMS_DEB_PREBUILT, see debian/rules) instead of a second compilation. Then: its metadata,
# files and maintainer scripts are checked; it is unpacked into a scratch root whose sms-gateway
# must answer --version and --check-config of every example, whose manual pages must render and
# whose documents' links must resolve; its postinst runs against stand-ins of the user and
# systemd tools that record what it asks for; and apt-get resolves its dependencies in a
# simulation. lintian, piuparts and the real systemd are scripts/package-check.sh and
# scripts/systemd-test.sh (on demand: root, minutes).
#
#   package_test.sh BUILD_DIR SOURCE_DIR
set -euo pipefail
build=$(cd "$1" && pwd) source=$(cd "$2" && pwd)
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT

fail() { echo "package_test: $*" >&2; exit 1; }

mkdir "$scratch/src"
cp -r "$source/debian" "$scratch/src/"
(cd "$scratch/src" && SMS_DEB_PREBUILT="$build" DH_QUIET=1 debian/rules binary) >"$scratch/dh.log" 2>&1 ||
  { cat "$scratch/dh.log"; fail "debhelper could not make the package"; }
deb=$(ls "$scratch"/sms-gateway_*_*.deb 2>/dev/null | head -1)
[ -n "$deb" ] || fail "no sms-gateway_*.deb in $scratch"

# The changelog's version is the program's.
version=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' "$source/CMakeLists.txt")
changelog_version=$(cd "$source" && dpkg-parsechangelog -SVersion)
[ "${changelog_version%%-*}" = "$version" ] ||
  fail "debian/changelog says $changelog_version, CMakeLists.txt $version: add a changelog entry (dch -v $version)"

info=$(dpkg-deb --info "$deb")
grep -q '^ Package: sms-gateway$' <<<"$info" || fail "package name: $info"
grep -q "^ Version: $changelog_version\$" <<<"$info" || fail "version is not $changelog_version: $info"
grep -q '^ Maintainer: .*@[a-z0-9.-]*\.[a-z]*>$' <<<"$info" || fail "maintainer address: $(grep Maintainer <<<"$info")"
grep -q '@localhost' <<<"$info" && fail "maintainer at localhost"
for dep in adduser procps libmodbus5 libssl3 libmosquitto1 libprotobuf-lite32 libyaml-cpp0.7; do
  grep -q "^ Depends:.*\b$dep\b" <<<"$info" || fail "no Depends on $dep: $(grep Depends <<<"$info")"
done
for script in postinst prerm postrm; do grep -q " $script " <<<"$info" || fail "no $script in the control archive"; done

contents=$(dpkg-deb --contents "$deb" | awk '{print $6}')
doc=./usr/share/doc/sms-gateway
for path in ./usr/bin/sms-gateway ./usr/bin/sms-sim ./lib/systemd/system/sms-gateway.service ./lib/systemd/system/sms-sim.service \
            ./usr/share/man/man1/sms-gateway.1.gz ./usr/share/man/man1/sms-sim.1.gz \
            ./usr/share/man/man5/sms-gateway.yaml.5.gz \
            $doc/README.md $doc/copyright $doc/changelog.gz $doc/docs/PLC_GUIDE.md $doc/docs/PROTOCOL.md \
            $doc/docs/INSTALL.md $doc/docs/SAFETY.md $doc/config/README.md $doc/config/examples/mixed.yaml $doc/examples \
            ./usr/share/sms-gateway/wireshark/sms_servo.lua ./usr/share/sms-gateway/prometheus/sms-gateway-rules.yml; do
  grep -qx "$path" <<<"$contents" || fail "$path is not in the package"
done

# Maintainer scripts: debhelper's systemd handling (not enabled on install, restarted on upgrade,
# stopped on removal, enable links removed on purge) and no direct systemctl of our own.
control="$scratch/control"
dpkg-deb -e "$deb" "$control"
grep -q 'deb-systemd-helper update-state' "$control/postinst" || fail "postinst does not register the unit's state"
grep -q "deb-systemd-helper --quiet was-enabled" "$control/postinst" ||
  fail "postinst may enable the service unconditionally (it needs a config first)"
grep -q 'deb-systemd-invoke .*restart\|_dh_action=restart' "$control/postinst" || fail "postinst does not restart on upgrade"
grep -q 'deb-systemd-invoke stop' "$control/prerm" || fail "prerm does not stop the service on removal"
grep -q 'deb-systemd-helper purge' "$control/postrm" || fail "postrm does not remove the enable links on purge"
for script in postinst prerm postrm; do sh -n "$control/$script" || fail "$script is not valid sh"; done

root="$scratch/root"
dpkg-deb -x "$deb" "$root"
"$root/usr/bin/sms-gateway" --version | grep -qx "sms-gateway $version" || fail "sms-gateway --version is not $version"
for example in "$root"/usr/share/doc/sms-gateway/examples/*.yaml; do
  "$root/usr/bin/sms-gateway" --check-config "$example" >/dev/null || fail "--check-config $(basename "$example") failed"
done
unit="$root/lib/systemd/system/sms-gateway.service"
grep -q '^ExecStart=/usr/bin/sms-gateway --config /etc/sms-gateway/config.yaml$' "$unit" ||
  fail "the unit does not start /usr/bin/sms-gateway: $(grep Exec "$unit")"
grep -q '^ExecStartPre=' "$unit" && fail "ExecStartPre= is back: RestartPreventExitStatus= does not cover it"
grep -q '^RestartPreventExitStatus=2$' "$unit" || fail "the unit restarts after a configuration error"
grep -q '^SupplementaryGroups=dialout$' "$unit" || fail "the unit lost its dialout group"
grep -q '^StateDirectory=sms-gateway$' "$unit" || fail "the unit has no StateDirectory"
# Shipped files describe the installed system, not the source tree.
if grep -rn -e 'build/bin' -e '/usr/local/bin' -e 'config/examples/' -e '\./scripts/' "$unit" \
     "$root/usr/share/doc/sms-gateway/config/examples" "$root/usr/share/doc/sms-gateway/README.md"; then
  fail "shipped files name paths of the source tree (above)"
fi
for page in man1/sms-gateway.1 man1/sms-sim.1 man5/sms-gateway.yaml.5; do
  LC_ALL=C.UTF-8 man -l "$root/usr/share/man/$page.gz" 2>/dev/null | grep -q . || fail "man $page does not render"
done
# Every relative link of the installed documents resolves where they are installed, to the file
# itself: the documents are not compressed (debian/rules), since a link to SAFETY.md finds nothing
# where only SAFETY.md.gz is.
compressed=$(grep '\.md\.gz$' <<<"$contents" || true)
[ -z "$compressed" ] || fail "Markdown documents are compressed, which breaks their links to one another: $compressed"
(cd "$root/usr/share/doc/sms-gateway" && find . -name '*.md' | while read -r md; do
  { grep -o '](\([^)#: ]*\)[)#]' "$md" || true; } | sed 's/^](//; s/[)#]$//' | while read -r target; do
    [ -n "$target" ] || continue
    [ -e "$(dirname "$md")/$target" ] || echo "$md: $target"
  done
done) >"$scratch/links"
[ ! -s "$scratch/links" ] || fail "installed documents link to files that are not installed: $(cat "$scratch/links")"

# postinst configure on a machine without the user: it creates group and user, puts the user in
# dialout, makes /etc/sms-gateway and the console's self-signed certificate and key (the key
# 0640 root:_sms-gateway); the unit is registered but not enabled or started.
stand_ins="$scratch/bin"
mkdir -p "$stand_ins"
for tool in addgroup adduser systemctl install deb-systemd-helper deb-systemd-invoke openssl chown chmod; do
  printf '#!/bin/sh\necho "%s $*" >>"%s"\n' "$tool" "$scratch/calls" >"$stand_ins/$tool"
done
# A first installation: no user yet, the unit never installed or enabled before.
printf '#!/bin/sh\nexit 2\n' >"$stand_ins/getent"
printf '#!/bin/sh\necho "deb-systemd-helper $*" >>"%s"\ncase "$*" in *was-enabled*|*debian-installed*) exit 1 ;; esac\n' \
  "$scratch/calls" >"$stand_ins/deb-systemd-helper"
chmod +x "$stand_ins"/*
PATH="$stand_ins:$PATH" sh "$control/postinst" configure || fail "postinst configure failed"
calls=$(cat "$scratch/calls")
grep -q '^addgroup --system --quiet _sms-gateway$' <<<"$calls" || fail "postinst did not create the group: $calls"
grep -q '^adduser --system --quiet --ingroup _sms-gateway .* _sms-gateway$' <<<"$calls" || fail "postinst did not create the user: $calls"
grep -q '^adduser --quiet _sms-gateway dialout$' <<<"$calls" || fail "postinst did not add _sms-gateway to dialout: $calls"
grep -q '^install -d -m 0755 /etc/sms-gateway$' <<<"$calls" || fail "postinst did not make /etc/sms-gateway: $calls"
if [ ! -e /etc/sms-gateway/console/console.key ] && [ ! -e /etc/sms-gateway/console/console.crt ]; then
  grep -q '^install -d -m 0750 -o root -g _sms-gateway /etc/sms-gateway/console$' <<<"$calls" ||
    fail "postinst did not make /etc/sms-gateway/console for the service group: $calls"
  grep -q '^openssl req -x509 .*-keyout /etc/sms-gateway/console/console.key -out /etc/sms-gateway/console/console.crt$' \
    <<<"$calls" || fail "postinst did not make the console's certificate: $calls"
  grep -q '^chown root:_sms-gateway /etc/sms-gateway/console/console.key /etc/sms-gateway/console/console.crt$' <<<"$calls" ||
    fail "postinst did not give the console's key to the service group: $calls"
  grep -q '^chmod 0640 /etc/sms-gateway/console/console.key$' <<<"$calls" ||
    fail "postinst left the console's key readable beyond the service group: $calls"
fi
grep -q '^deb-systemd-helper enable' <<<"$calls" && fail "postinst enabled the service: $calls"

# apt on this Debian 12 machine resolves every Depends; a simulation changes nothing.
if command -v apt-get >/dev/null; then
  apt-get install --simulate "$deb" >"$scratch/apt.log" 2>&1 ||
    { cat "$scratch/apt.log"; fail "apt-get cannot install the package (dependencies)"; }
  grep -q '^Inst sms-gateway ' "$scratch/apt.log" || fail "apt-get would not install it: $(cat "$scratch/apt.log")"
fi

echo "package_test: $(basename "$deb") ok ($(du -k "$deb" | cut -f1) KiB)"
