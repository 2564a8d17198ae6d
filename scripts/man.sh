#!/usr/bin/env bash
# Makes the manual pages in docs/man/ from their one source each, so they cannot drift:
#   sms-gateway(1)       `sms-gateway --help` and each tool's `--help` (help2man), plus
#                        docs/man/sms-gateway.h2m (exit status, files, signals, see also);
#   sms-sim(1)           `sms-sim --help` (help2man), plus docs/man/sms-sim.h2m;
#   sms-gateway.yaml(5)  config/README.md, the configuration reference (pandoc).
# The test command regenerates them from its build and fails when they differ
# (tests/docs/man_pages_test.sh); after changing --help or config/README.md run this and commit.
#
#   scripts/man.sh BIN_DIR [OUT_DIR]     # BIN_DIR holds sms-gateway and sms-sim; OUT_DIR: docs/man
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
[ $# -ge 1 ] || { sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
bin=$(cd "$1" && pwd)
out=$(mkdir -p "${2:-$root/docs/man}" && cd "${2:-$root/docs/man}" && pwd)
for tool in help2man pandoc; do
  command -v "$tool" >/dev/null || { echo "man.sh: $tool is missing (apt-get install $tool)" >&2; exit 1; }
done

# One date for every page: the package's changelog entry (reproducible, and the same in the test).
export SOURCE_DATE_EPOCH
SOURCE_DATE_EPOCH=$(cd "$root" && dpkg-parsechangelog -STimestamp)
version=$(sed -n 's/^project(sms_gateway VERSION \([0-9.]*\).*/\1/p' "$root/CMakeLists.txt")
export PATH="$bin:$PATH" COLUMNS=100
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# The tools' own --help, verbatim, as a section of sms-gateway(1).
{
  cat "$root/docs/man/sms-gateway.h2m"
  echo "[TOOLS]"
  echo "Each tool is a subcommand; its options:"
  for tool in scan set-id set-baud calibrate-middle factory-reset dump forward tags; do
    echo ".SS \"sms-gateway $tool\""
    echo ".nf"
    sms-gateway "$tool" --help | sed -e 's/\\/\\e/g' -e 's/^\./\\\&./' -e 's/^'"'"'/\\\&'"'"'/'
    echo ".fi"
  done
} >"$work/sms-gateway.h2m"

help2man --no-info --version-string="$version" --source="sms-gateway $version" --section=1 \
  --name="Modbus TCP gateway for RS-485 serial-bus servos" \
  --include="$work/sms-gateway.h2m" --output="$out/sms-gateway.1" sms-gateway
help2man --no-info --version-string="$version" --source="sms-gateway $version" --section=1 \
  --name="simulated RS-485 servos on a pseudo-terminal" \
  --include="$root/docs/man/sms-sim.h2m" --output="$out/sms-sim.1" sms-sim

# config/README.md as sms-gateway.yaml(5): its links become plain text (the files are named).
date=$(date -u -d "@$SOURCE_DATE_EPOCH" +%Y-%m-%d)
sed -e '1s/^# .*/# NAME\n\nsms-gateway.yaml - the sms-gateway configuration file\n\n# DESCRIPTION\n/' \
    -e 's/^## /# /' "$root/config/README.md" |
  pandoc --from=gfm --to=man --standalone \
    --metadata=title=SMS-GATEWAY.YAML --metadata=section=5 --metadata=date="$date" \
    --metadata=footer="sms-gateway $version" --metadata=header="File formats" \
    --output="$work/sms-gateway.yaml.5"
# Long unbreakable words (JSON samples, address lists, OIDs) in narrow table cells: allow a line
# break after their , . / : ; (groff's \: is an invisible break point), so the page renders
# without warnings at any width; and left-aligned text.
python3 - "$work/sms-gateway.yaml.5" "$out/sms-gateway.yaml.5" <<'PY'
import re, sys
def breakable(word):
    if len(word) < 16: return word
    out, depth = [], 0
    for i, c in enumerate(word):
        out.append(c)
        if c == "[" and i > 0 and word[i - 1] in "\\f(" : depth += 1
        elif c == "]" and depth: depth -= 1
        elif c in ",./:;" and not depth and i + 1 < len(word): out.append("\\:")
    return "".join(out)
lines = open(sys.argv[1], encoding="utf-8").read().split("\n")
lines = [l if l.startswith((".", "'")) or not l else " ".join(breakable(w) for w in l.split(" ")) for l in lines]
# Left-aligned text (no justification): narrow table cells cannot be justified without warnings.
th = next(i for i, l in enumerate(lines) if l.startswith(".TH "))
lines.insert(th + 1, ".ad l")
open(sys.argv[2], "w", encoding="utf-8").write("\n".join(lines))
PY
echo "man.sh: $out/sms-gateway.1 $out/sms-sim.1 $out/sms-gateway.yaml.5"
