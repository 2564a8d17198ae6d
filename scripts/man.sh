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
    # The environment block is the whole program's footer, already under OPTIONS: not repeated per tool.
    sms-gateway "$tool" --help | awk '/^Environment \(/ { skip = 1 } skip && /^$/ { skip = 0; next } !skip' |
      sed -e 's/\\/\\e/g' -e 's/^\./\\\&./' -e 's/^'"'"'/\\\&'"'"'/'
    echo ".fi"
  done
} >"$work/sms-gateway.h2m"

help2man --no-info --version-string="$version" --source="sms-gateway $version" --section=1 \
  --name="Modbus TCP gateway for RS-485 serial-bus servos" \
  --include="$work/sms-gateway.h2m" --output="$out/sms-gateway.1" sms-gateway
help2man --no-info --version-string="$version" --source="sms-gateway $version" --section=1 \
  --name="simulated RS-485 servos on a pseudo-terminal" \
  --include="$root/docs/man/sms-sim.h2m" --output="$work/sms-sim.1" sms-sim
# help2man fills the indented example and command lines of sms-sim --help into one paragraph:
# its EXAMPLES section is made again from that text, indented lines kept as they are (.nf).
sms-sim --help >"$work/sms-sim.help"
python3 - "$work/sms-sim.1" "$work/sms-sim.help" "$out/sms-sim.1" <<'PY'
import re, sys
page = open(sys.argv[1], encoding="utf-8").read()
help_lines = open(sys.argv[2], encoding="utf-8").read().split("\n")
start = help_lines.index("Examples:") + 1
end = next(i for i in range(start, len(help_lines)) if help_lines[i].startswith("Usage:"))
def roff(text):
    text = text.replace("\\", "\\e").replace("-", "\\-")
    return "\\&" + text if text.startswith((".", "'")) else text
section, verbatim, new_paragraph = [".SH EXAMPLES"], False, True
for line in help_lines[start:end]:
    indented = line.startswith("  ")
    if not line.strip() or indented != verbatim:
        if verbatim: section.append(".fi")
        verbatim, new_paragraph = False, True
    if not line.strip():
        continue
    if new_paragraph:
        section += [".PP", ".nf"] if indented else [".PP"]
        verbatim, new_paragraph = indented, False
    section.append(roff(line[2:] if indented else line))
if verbatim: section.append(".fi")
page, n = re.subn(r"^\.SH EXAMPLES\n.*?(?=^\.SH )", lambda m: "\n".join(section) + "\n", page, flags=re.M | re.S)
assert n == 1, "sms-sim(1) has no EXAMPLES section"
open(sys.argv[3], "w", encoding="utf-8").write(page)
PY

# A table in a manual page is set by tbl, which cannot break a row across pages (it warns when
# a row ends at a page foot, which moves with any edit of the text): the reference tables become
# definition lists, a term per row: the first cell, the middle cells in parentheses ("default
# 60", "required", "replaces logging.level"), then the last cell as its text. A link to the
# examples directory becomes its installed path (argv[1]).
tables_to_lists='
import json, sys
doc = json.load(sys.stdin)
def text(inlines):
    return "".join(i.get("c", " ") if i["t"] == "Str" else text(i["c"]) if i["t"] in ("Strong", "Emph")
                   else i["c"][1] if i["t"] == "Code" else " " for i in inlines)
def cell_inlines(cell):
    return [i for b in cell[4] for i in b["c"]]
def rows(table):
    head = [r[1] for r in table[3][1]]
    body = [r[1] for tb in table[4] for r in tb[3]]
    return head[0] if head else None, body
def as_list(table):
    header, body = rows(table)
    names = [text(cell_inlines(c)).strip() for c in header] if header else []
    items = []
    for row in body:
        cells = [cell_inlines(c) for c in row]
        term = list(cells[0])
        for column in range(1, len(cells) - 1):
            value, name = cells[column], names[column] if column < len(names) else ""
            if text(value).strip() == "required":
                term += [{"t": "Space"}, {"t": "Str", "c": "(required)"}]
            else:
                term += [{"t": "Space"}, {"t": "Str", "c": "(" + name}, {"t": "Space"}] + value + [{"t": "Str", "c": ")"}]
        items.append([term, [[{"t": "Para", "c": cells[-1]}]]])
    return {"t": "DefinitionList", "c": items}
def walk(node):
    if isinstance(node, list):
        return [walk(n) for n in node]
    if not isinstance(node, dict):
        return node
    if node.get("t") == "Table":
        return as_list(node["c"])
    if node.get("t") == "Link" and node["c"][2][0].rstrip("/") == "examples":
        return {"t": "Code", "c": [["", [], []], sys.argv[1]]}
    return {k: walk(v) for k, v in node.items()}
doc["blocks"] = walk(doc["blocks"])
json.dump(doc, sys.stdout)
'
# config/README.md as sms-gateway.yaml(5): its links become plain text (the files are named), the
# examples directory its installed path, and the documents it names are said where to find.
date=$(date -u -d "@$SOURCE_DATE_EPOCH" +%Y-%m-%d)
doc=/usr/share/doc/sms-gateway
{
  sed -e '1s/^# .*/# NAME\n\nsms-gateway.yaml - the sms-gateway configuration file\n\n# DESCRIPTION\n/' \
      -e 's/^## /# /' "$root/config/README.md"
  printf '\n# SEE ALSO\n\n**sms-gateway**(1), **sms-sim**(1).\n'
  printf 'The documents named `docs/...` are installed in `%s/docs/`, compressed (read them with `zless`).\n' "$doc"
} |
  pandoc --from=gfm --to=json | python3 -c "$tables_to_lists" "$doc/examples/" |
  pandoc --from=json --to=man --standalone \
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
