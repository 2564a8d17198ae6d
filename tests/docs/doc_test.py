#!/usr/bin/python3
"""The documents' runnable blocks, run against the simulator, and their links.

Usage: doc_test.py BIN_DIR SOURCE_DIR

1. Every ```sh block of README.md carries a marker on the line before it:
   `<!-- doc-test -->` (run here) or `<!-- doc-test: skip — why, and what runs it instead -->`.
   In docs/PLC_GUIDE.md the blocks marked `<!-- doc-test -->` (sh or python) run too.
2. The marked blocks run in order against `sms-gateway --simulate` on a free port of 127.0.0.1
   (the documents say 5020; the test puts its port there), with BIN_DIR first on PATH, in a
   scratch directory; each must exit 0.
3. Every relative Markdown link in the project's documents resolves to a file (and, with
   #anchor, to a heading of it), and no file refers to anything outside the repository
   (a specs folder beside the checkout, or specs other than the project's own docs/PROTOCOL.md and
   docs/PLC_GUIDE.md), nor cites a tracker number.
4. Each Dockerfile copies every folder the build needs.
5. Every metric family the gateway's sources name (`"sms_gateway_..."` in gateway/) has its row
   in docs/OPERATIONS.md.
"""
import os
import re
import subprocess
import sys
import tempfile
import time

MARK = re.compile(r"^<!-- doc-test(?::\s*skip\b(?P<why>.*?))?\s*-->$")
FENCE = re.compile(r"^```(\w*)\s*$")
# The gateway's log line for a timed move refused because a servo did not answer its read in time.
NOT_READ_IN_TIME = re.compile(r"a servo was not read, no move: .*(no answer|is offline)")
# mbpoll's words for exception 0x0B, and the gateway's log line for a servo that stopped answering.
SERVO_SILENT = "Target device failed to respond"
WENT_OFFLINE = re.compile(r"servo \d+ offline \(.*no answer")


def blocks(path):
    """(line, language, marker or None, text) of every fenced block."""
    lines = open(path, encoding="utf-8").read().split("\n")
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m and m.group(1):
            start, lang = i, m.group(1)
            j = i + 1
            while j < len(lines) and lines[j] != "```":
                j += 1
            marker = MARK.match(lines[start - 1]) if start > 0 else None
            out.append((start + 1, lang, marker, "\n".join(lines[start + 1:j])))
            i = j + 1
        else:
            i += 1
    return out


def slug(heading):
    """GitHub's anchor for a heading."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def check_links(source):
    errors = []
    docs = subprocess.run(["git", "-C", source, "ls-files", "*.md"], capture_output=True, text=True).stdout.split()
    docs = docs or [os.path.relpath(os.path.join(d, f), source) for d, _, fs in os.walk(source)
                    if "/build" not in d and "/.git" not in d for f in fs if f.endswith(".md")]
    for doc in docs:
        text = open(os.path.join(source, doc), encoding="utf-8").read()
        text = re.sub(r"```.*?```", "", text, flags=re.S)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"^[a-z]+:", target) or target.startswith("#"):
                continue
            file, _, anchor = target.partition("#")
            path = os.path.normpath(os.path.join(source, os.path.dirname(doc), file))
            if not os.path.exists(path):
                errors.append(f"{doc}: link to {target}: no such file")
            elif anchor and path.endswith(".md"):
                heads = [slug(h) for h in re.findall(r"^#+ (.*)$", open(path, encoding="utf-8").read(), re.M)]
                if anchor not in heads:
                    errors.append(f"{doc}: link to {target}: no heading with that anchor")
    return errors


def check_outside_references(source):
    # Code comments are rewritten to the project's documents separately; everything else must
    # already name only what the repository holds.
    files = subprocess.run(["git", "-C", source, "ls-files"], capture_output=True, text=True).stdout.split()
    errors = []
    for f in files:
        if f.startswith("tests/fuzz/corpus"):
            continue
        try:
            text = open(os.path.join(source, f), encoding="utf-8").read()
        except (UnicodeDecodeError, IsADirectoryError, FileNotFoundError):
            continue
        for n, line in enumerate(text.split("\n"), 1):
            if f == "tests/docs/doc_test.py":
                continue
            if re.search(r"\.\./shared/|\bSPEC\.md\b|\bSPEC §|(?<![/\w])MODBUS_MAP\.md|\bSTYLE\.md\b|\bCONTAINERS\.md\b", line):
                errors.append(f"{f}:{n}: refers to a document outside the repository: {line.strip()[:100]}")
            # The tracker is not part of the product: a reader of the repository cannot look it up.
            if re.search(r"\bissues? \d+\b", line, re.IGNORECASE):
                errors.append(f"{f}:{n}: cites a tracker number: {line.strip()[:100]}")
    return errors


def check_metrics_documented(source):
    served = set()
    for root, _, names in os.walk(os.path.join(source, "gateway")):
        for name in names:
            if name.endswith((".cpp", ".h")):
                text = open(os.path.join(root, name), encoding="utf-8").read()
                served.update(re.findall(r'"(sms_gateway_[a-z0-9_]+)"', text))
    operations = open(os.path.join(source, "docs/OPERATIONS.md"), encoding="utf-8").read()
    documented = set(re.findall(r"^\| `(sms_gateway_[a-z0-9_]+)`", operations, re.MULTILINE))
    return [f"docs/OPERATIONS.md: no row for the metric family {family} (the gateway serves it)"
            for family in sorted(served - documented)]


def check_dockerfiles(source):
    """Each Dockerfile copies every folder the top-level CMakeLists.txt builds or includes from
    (tests and benchmarks are off in the images): a missing one fails only at image build time."""
    cmake = open(os.path.join(source, "CMakeLists.txt"), encoding="utf-8").read()
    folders = set()
    for path in re.findall(r"^\s*add_subdirectory\((\S+?)\)", cmake, re.MULTILINE):
        top = path.split("/")[0]
        if top not in ("tests", "bench"):
            folders.add(top)
    folders.update(path.split("/")[0] for path in re.findall(r"^\s*include\((\S+?)\)", cmake, re.MULTILINE))
    errors = []
    for dockerfile in ("docker/Dockerfile", "docker/Dockerfile.cross"):
        text = open(os.path.join(source, dockerfile), encoding="utf-8").read()
        copied = {path.split("/")[0] for path in re.findall(r"^COPY (?!--from)(\S+)", text, re.MULTILINE)}
        for folder in sorted(folders - copied):
            errors.append(f"{dockerfile}: does not COPY {folder}/, which CMakeLists.txt builds or includes from")
    return errors


def start_gateway(bin_dir, scratch):
    log = open(os.path.join(scratch, "gateway.log"), "w+")
    gateway = subprocess.Popen([os.path.join(bin_dir, "sms-gateway"), "--simulate", "--listen", "127.0.0.1:0"],
                               stdout=log, stderr=subprocess.STDOUT, cwd=scratch)
    deadline = time.monotonic() + 30
    port = None
    while time.monotonic() < deadline and gateway.poll() is None:
        text = open(log.name).read()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", text)
        if m and "servos online" in text:
            port = m.group(1)
            break
        time.sleep(0.1)
    if port is None:
        gateway.kill()
        sys.exit("doc_test: the simulated gateway did not start:\n" + open(log.name).read())
    return gateway, port


def main():
    bin_dir, source = os.path.abspath(sys.argv[1]), os.path.abspath(sys.argv[2])
    errors = []
    runnable = []
    for doc, must_mark in (("README.md", True), ("docs/PLC_GUIDE.md", False)):
        for line, lang, marker, text in blocks(os.path.join(source, doc)):
            if marker is None:
                if must_mark and lang == "sh":
                    errors.append(f"{doc}:{line}: sh block without a doc-test marker (run it, or say why not)")
                continue
            if marker.group("why") is not None:
                if len(marker.group("why").strip(" —-")) < 10:
                    errors.append(f"{doc}:{line}: doc-test skip without a reason")
                continue
            if lang not in ("sh", "python"):
                errors.append(f"{doc}:{line}: runnable block of language '{lang}'")
                continue
            runnable.append((doc, line, lang, text))
    errors += check_links(source)
    errors += check_outside_references(source)
    errors += check_metrics_documented(source)
    errors += check_dockerfiles(source)

    with tempfile.TemporaryDirectory() as scratch:
        gateway, port = start_gateway(bin_dir, scratch)
        env = dict(os.environ, PATH=bin_dir + os.pathsep + os.environ["PATH"])
        try:
            for doc, line, lang, text in runnable:
                text = text.replace("-p 5020", "-p " + port).replace("port=5020", "port=" + port)
                command = ["bash", "-euo", "pipefail", "-c", text] if lang == "sh" else ["/usr/bin/python3", "-c", text]
                for attempt in range(1, 4):
                    logged_before = os.path.getsize(os.path.join(scratch, "gateway.log"))
                    run = subprocess.run(command, cwd=scratch, env=env, capture_output=True, text=True, timeout=60)
                    # A servo that missed its response timeouts (20 ms on the simulated bus) is offline
                    # until its probe, and the gateway answers 0x0B for it, nothing written; a timed move
                    # whose servos were not all read in time is refused so too (docs/PLC_GUIDE.md
                    # "Timed group moves"). That is the gateway's rule where a loaded machine holds the
                    # simulator back: after one probe period the block runs again, as a PLC would ask
                    # again, at most 3 times, and says so; any other failure is one.
                    with open(os.path.join(scratch, "gateway.log"), "rb") as log:
                        whole = log.read()
                    since = whole[logged_before:].decode(errors="replace").splitlines()
                    late = [l for l in since if NOT_READ_IN_TIME.search(l)]
                    if not late and SERVO_SILENT in run.stdout + run.stderr:
                        late = [l for l in whole.decode(errors="replace").splitlines() if WENT_OFFLINE.search(l)][-1:]
                    if run.returncode == 0 or not late or attempt == 3:
                        break
                    print(f"doc_test: {doc}:{line}: a servo did not answer in time ({late[0].strip()}): the block runs again")
                    time.sleep(1.2)
                if run.returncode != 0:
                    # The gateway's side of it: what it logged while the block ran (refusals, late servos).
                    logged = open(os.path.join(scratch, "gateway.log")).read().splitlines()[-15:]
                    errors.append(f"{doc}:{line}: {lang} block exited {run.returncode}:\n{run.stdout}{run.stderr}"
                                  "the gateway's last log lines:\n  " + "\n  ".join(logged))
                else:
                    print(f"doc_test: {doc}:{line}: {lang} block ok")
        finally:
            gateway.terminate()
            gateway.wait(timeout=20)
    for e in errors:
        print("doc_test: " + e, file=sys.stderr)
    print(f"doc_test: {len(runnable)} blocks run, {len(errors)} problems")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
