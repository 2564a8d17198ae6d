#!/usr/bin/env bash
# The manual pages in docs/man/ are what scripts/man.sh makes from this build's --help and from
# config/README.md (they cannot drift), and each renders without a groff error.
#
#   man_pages_test.sh BIN_DIR SOURCE_DIR
set -euo pipefail
bin=$1 source=$2
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
"$source/scripts/man.sh" "$bin" "$scratch" >/dev/null
status=0
for page in sms-gateway.1 sms-sim.1 sms-gateway.yaml.5; do
  if ! diff -u "$source/docs/man/$page" "$scratch/$page" >"$scratch/$page.diff"; then
    head -40 "$scratch/$page.diff" >&2
    echo "man_pages_test: docs/man/$page is stale: run scripts/man.sh build-asan/bin and commit it" >&2
    status=1
  fi
  # Rendered as lintian does (120 columns): any groff or tbl message fails, warnings included.
  LC_ALL=C.UTF-8 MANWIDTH=120 man --warnings -E UTF-8 -l -Tutf8 -Z "$source/docs/man/$page" \
    2>"$scratch/groff.log" >"$scratch/page.txt" || true
  if grep -q . "$scratch/groff.log" || [ ! -s "$scratch/page.txt" ]; then
    cat "$scratch/groff.log" >&2; echo "man_pages_test: $page does not render cleanly" >&2; status=1
  fi
done
[ "$status" -eq 0 ] && echo "man_pages_test: sms-gateway(1), sms-sim(1), sms-gateway.yaml(5) current and rendering"
exit "$status"
