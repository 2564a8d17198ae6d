#!/usr/bin/env python3
"""A check of every translation unit with a result cache, as ccache does for compiles:
  tidy  clang-tidy (.clang-tidy at the root), over BUILD_DIR's compile commands;
  gcc   GCC 12's front end (-fsyntax-only) with the build's own flags (-Wall -Wextra -Werror):
        every error and warning GCC gives while it parses, checks and instantiates the file.

A file that passed before is not checked again while its preprocessed source (with every
header it includes), its compile flags, the tool's configuration and version are unchanged:
the key is a SHA-256 of those. Only passing runs are remembered, so a finding shows every time.
The checkout's own path is left out of the key (as ccache's base_dir does): another clone of the
same sources on the same machine finds the results of this one.
The caches live in $SMS_CHECK_CACHE (default ~/.cache/sms-gateway: clang-tidy/, gcc-syntax/); deleting them only
costs time.

usage: check_once.py tidy|gcc BUILD_DIR [FILE...]   exit 0: no findings; 1: findings (printed); 2: usage
Without files: tidy checks the product's sources (protocol/, modbus_map/, config/, gateway/,
simulator/: tests and benchmarks are not, gtest's macros trip bugprone-* without finding
anything); gcc checks every file of BUILD_DIR's compile database, the sources the build
generates (protobuf code, the console's embedded pages) made first, alone.

Of those, only the files a change touched, with every file that includes a touched header, are
checked against the commit the change builds on (docs/DECISIONS.md "The checks look at what
changed"): the tree passed both checks there, as every commit passes the test command before it
is made. The base is $SMS_CHECK_BASE where set (a revision; "all" for the full sweep), else the
merge-base of HEAD with main, or HEAD's parent where that is HEAD itself and nothing is
uncommitted. Which files include which header is read from the dependency log of
$SMS_CHECK_DEPS (a ninja build of the same sources, default build-asan, which the test command
has just built). The full sweep is made where the base is unknown (no main, a shallow clone,
CI=true: CI's fresh clone cannot tell which commits are new), where the change touched what
shapes every compile or check (a CMakeLists.txt, cmake/, .clang-tidy, the scripts that run the
checks), and where this machine's cache saw another version of the tool.
"""
import concurrent.futures
import hashlib
import json
import os
import pathlib
import re
import shlex
import subprocess
import sys


def compile_args(entry):
    args = entry["arguments"] if "arguments" in entry else shlex.split(entry["command"])
    # Preprocess instead of compiling: drop the output and -c, keep every flag that shapes the source.
    out, skip = [], False
    for arg in args:
        if skip:
            skip = False
            continue
        if arg == "-o":
            skip = True
            continue
        if arg == "-c":
            continue
        out.append(arg)
    # ccache as a launcher is not part of the compile.
    if out and os.path.basename(out[0]) == "ccache":
        out = out[1:]
    return out


def output_of(entry):
    args = entry["arguments"] if "arguments" in entry else shlex.split(entry["command"])
    return args[args.index("-o") + 1] if "-o" in args else None


# A batch of CMake's unity build (CMAKE_UNITY_BUILD, scripts/test.sh): a generated source that
# includes the target's sources by their absolute paths.
UNITY_MEMBER = re.compile(r'^#include "(/[^"]+)"$', re.M)


def unity_members(entry):
    """The sources a unity batch compiles, or None for an entry of one source."""
    path = os.path.join(entry["directory"], entry["file"])
    if "/Unity/unity_" not in path or not os.path.isfile(path):
        return None
    return UNITY_MEMBER.findall(pathlib.Path(path).read_text())


def database_of(build):
    """BUILD's compile commands, an entry per source: a unity batch's entry stands for each of its
    sources, with the batch's flags (every source of a batch is one target's)."""
    entries = []
    for entry in json.loads((build / "compile_commands.json").read_text()):
        members = unity_members(entry)
        if members is None:
            entries.append(entry)
            continue
        batch = os.path.join(entry["directory"], entry["file"])
        for member in members:
            one = dict(entry, file=member)
            if "arguments" in one:
                one["arguments"] = [member if a in (entry["file"], batch) else a for a in one["arguments"]]
            else:
                one["command"] = shlex.join(member if a in (entry["file"], batch) else a
                                            for a in shlex.split(one["command"]))
            entries.append(one)
    return entries


def git(root, *args):
    return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)


def change_base(root):
    """The commit the change builds on, and how it was found; None where it is not known."""
    asked = os.environ.get("SMS_CHECK_BASE", "")
    if asked == "all":
        return None, "SMS_CHECK_BASE=all"
    if asked:
        found = git(root, "rev-parse", "-q", "--verify", asked + "^{commit}")
        if found.returncode != 0:
            raise SystemExit("check_once: SMS_CHECK_BASE=%s is no commit here" % asked)
        return found.stdout.strip(), "SMS_CHECK_BASE=" + asked
    if os.environ.get("CI") == "true":
        return None, "CI=true: a fresh clone cannot tell which commits are new"
    head = git(root, "rev-parse", "-q", "--verify", "HEAD^{commit}").stdout.strip()
    if not head:
        return None, "no commit yet"
    for main in ("main", "origin/main"):
        merge_base = git(root, "merge-base", "HEAD", main)
        if merge_base.returncode == 0:
            break
    else:
        return None, "no main branch to compare with"
    base = merge_base.stdout.strip()
    uncommitted = git(root, "status", "--porcelain", "--untracked-files=normal").stdout.strip()
    if base == head and not uncommitted:
        parent = git(root, "rev-parse", "-q", "--verify", "HEAD^1")
        if parent.returncode != 0:
            return None, "HEAD's parent is not here (a shallow clone?)"
        return parent.stdout.strip(), "HEAD's parent (HEAD is %s, nothing uncommitted)" % main
    return base, "the merge-base of HEAD and " + main


# A change to these shapes every compile or check: it is checked by the full sweep.
SWEEP_ALL_NAMES = ("CMakeLists.txt", ".clang-tidy")
SWEEP_ALL_PATHS = ("cmake/", "scripts/check_once.py", "scripts/tidy.sh", "scripts/gcc-check.sh", "scripts/test.sh")


def changed_since(root, base):
    """The files (real paths) that differ between base and the working tree, untracked ones
    included; and the first of them that calls for the full sweep, if any."""
    names = git(root, "diff", "--name-only", "--no-renames", base).stdout.splitlines()
    names += git(root, "ls-files", "--others", "--exclude-standard").stdout.splitlines()
    sweep = next((n for n in names if os.path.basename(n) in SWEEP_ALL_NAMES or n.startswith(SWEEP_ALL_PATHS)
                  or n.endswith(".cmake")), None)
    return {os.path.realpath(root / n) for n in names if n}, sweep


def dependencies(deps_build):
    """{source: the real paths of the files it read} from the ninja dependency log of deps_build;
    a source whose record is missing or stale is left out (and so counts as touched). The sources
    of a unity batch each get the batch's record less the batch's other sources: a header any of
    them includes counts for all of them."""
    database = json.loads((deps_build / "compile_commands.json").read_text())
    sources_of = {}
    for entry in database:
        output = output_of(entry)
        if output:
            members = unity_members(entry) or [os.path.join(entry["directory"], entry["file"])]
            sources_of[os.path.normpath(os.path.join(entry["directory"], output))] = [os.path.abspath(m) for m in members]
    log = subprocess.run(["ninja", "-C", str(deps_build), "-t", "deps"], capture_output=True, text=True,
                         check=True).stdout
    records, current = [], None
    for line in log.splitlines():
        if not line.startswith(" "):
            current = None
            if ": #deps" in line and line.rstrip().endswith("(VALID)"):
                sources = sources_of.get(os.path.normpath(os.path.join(deps_build, line.split(": #deps")[0])))
                if sources is not None:
                    current = set()
                    records.append((sources, current))
        elif current is not None and line.strip():
            current.add(os.path.realpath(os.path.join(deps_build, line.strip())))
    result = {}
    for sources, read in records:
        batch = {os.path.realpath(source) for source in sources}
        for source in sources:
            result[source] = read - (batch - {os.path.realpath(source)})
    return result


def key_of(entry, config, version, root):
    args = compile_args(entry)
    preprocessed = subprocess.run(args + ["-E", "-P", "-o", "-"], cwd=entry["directory"], capture_output=True,
                                  check=True).stdout
    # The checkout's path (in -I flags, and in __FILE__ where a macro expands it) is not the source.
    anywhere = str(root).encode()
    flags = "\0".join(args).encode().replace(anywhere, b"@ROOT@")
    digest = hashlib.sha256()
    for part in (version, config, flags, preprocessed.replace(anywhere, b"@ROOT@")):
        digest.update(part)
        digest.update(b"\0")
    return digest.hexdigest()


class Tidy:
    name, cache_dir = "tidy", "clang-tidy"
    advice = "fix them, or say why not with NOLINT(check) and a reason"

    def __init__(self, root, build, entries):
        # clang-tidy finds a file's flags in a compile database: one with an entry per source,
        # where the build's own lists unity batches (database_of).
        self.build = build / "tidy-database"
        self.build.mkdir(exist_ok=True)
        (self.build / "compile_commands.json").write_text(json.dumps(list(entries.values()), indent=1))
        self.config = (root / ".clang-tidy").read_bytes()
        self.version = subprocess.run(["clang-tidy", "--version"], capture_output=True, check=True).stdout

    def default_files(self, root, entries):
        listed = subprocess.run(["git", "ls-files", "protocol/*.cpp", "modbus_map/*.cpp", "config/*.cpp",
                                 "gateway/*.cpp", "simulator/*.cpp"], cwd=root, capture_output=True, text=True,
                                check=True).stdout.split()
        return [str(root / f) for f in listed]

    def run(self, entry, path):
        return subprocess.run(["clang-tidy", "-p", str(self.build), "--quiet", path], capture_output=True, text=True)


class GccFrontEnd:
    name, cache_dir = "gcc", "gcc-syntax"
    advice = "GCC 12 is the compiler of packagers, scripts/bench.sh and the container image: fix them for it too"

    def __init__(self, root, build, entries):
        self.build = build
        self.config = b"-fsyntax-only"
        compiler = compile_args(next(iter(entries.values())))[0] if entries else "g++"
        self.version = subprocess.run([compiler, "--version"], capture_output=True, check=True).stdout

    def default_files(self, root, entries):
        build = os.path.abspath(self.build)
        for generated in (os.path.relpath(f, build) for f in entries if f.startswith(build + "/")):
            # Only the command that makes the file (protoc, the console's page embedding; ninja lists
            # it last): `cmake --build --target` would first compile every library its target links,
            # with GCC at -O2, which is most of a cold check's time and none of its use.
            commands = subprocess.run(["ninja", "-C", build, "-t", "commands", generated], capture_output=True,
                                      text=True, check=True).stdout.splitlines()
            made = subprocess.run(commands[-1], shell=True, capture_output=True, text=True)
            if made.returncode != 0:
                raise SystemExit("gcc: could not make %s, which the build generates (%s):\n%s"
                                 % (generated, commands[-1], made.stdout + made.stderr))
        return list(entries)

    def run(self, entry, path):
        return subprocess.run(compile_args(entry) + ["-fsyntax-only"], cwd=entry["directory"], capture_output=True,
                              text=True)


def main():
    checks = {"tidy": Tidy, "gcc": GccFrontEnd}
    if len(sys.argv) < 3 or sys.argv[1] not in checks:
        print(__doc__, file=sys.stderr)
        return 2
    build, files = pathlib.Path(sys.argv[2]), [os.path.abspath(f) for f in sys.argv[3:]]
    root = pathlib.Path(__file__).resolve().parent.parent
    if not (build / "compile_commands.json").is_file():
        print("%s: %s/compile_commands.json is missing: configure %s first (scripts/test.sh does)"
              % (sys.argv[1], build, build), file=sys.stderr)
        return 2
    entries = {os.path.abspath(os.path.join(e["directory"], e["file"])): e for e in database_of(build)}
    check = checks[sys.argv[1]](root, build, entries)
    cache = pathlib.Path(os.environ.get("SMS_CHECK_CACHE", pathlib.Path.home() / ".cache/sms-gateway")) / check.cache_dir
    cache.mkdir(parents=True, exist_ok=True)
    # This version of the tool with this configuration has run here (a marker beside the results).
    tool = cache / ("tool-" + hashlib.sha256(check.version + b"\0" + check.config).hexdigest()[:16])
    scope = "the files named"
    if not files:
        files = check.default_files(root, entries)
        base, how = change_base(root)
        sweep = None
        if base is not None:
            changed, sweep = changed_since(root, base)
            if sweep:
                sweep = "the change touches %s" % sweep
            elif not tool.exists() and any(cache.glob("tool-*")):
                sweep = "this machine's cache saw another version of the tool or its configuration"
        if base is None or sweep:
            scope = "the full sweep (%s)" % (sweep or how)
        else:
            deps_build = pathlib.Path(os.environ.get("SMS_CHECK_DEPS", root / "build-asan"))
            if not (deps_build / "compile_commands.json").is_file():
                print("%s: %s/compile_commands.json is missing: build %s first (scripts/test.sh does), or set "
                      "SMS_CHECK_BASE=all" % (check.name, deps_build, deps_build), file=sys.stderr)
                return 2
            deps = dependencies(deps_build)
            everything = len(files)
            files = [f for f in files if os.path.realpath(f) in changed or f not in deps or deps[f] & changed]
            scope = "%d of %d files: those touched since %s, %s, or including a touched header" % (
                len(files), everything, base[:12], how)
    missing = [f for f in files if f not in entries]
    if missing:
        print("%s: not in %s/compile_commands.json: %s" % (check.name, build, " ".join(missing)), file=sys.stderr)
        return 2
    print("%s: %s" % (check.name, scope))

    def one(path):
        try:
            key = key_of(entries[path], check.config, check.version, root)
        except subprocess.CalledProcessError as error:
            return path, False, "preprocessing failed: " + error.stderr.decode(errors="replace")
        stamp = cache / key
        if stamp.exists():
            return path, True, None
        run = check.run(entries[path], path)
        if run.returncode == 0:
            stamp.touch()
            return path, False, None
        return path, False, run.stdout + run.stderr

    failed, cached = 0, 0
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        for path, hit, findings in pool.map(one, files):
            cached += hit
            if findings is not None:
                failed += 1
                lines = [l for l in findings.splitlines() if "warnings generated" not in l and "Suppressed" not in l
                         and "Use -header-filter" not in l]
                print("\n".join(lines), file=sys.stderr)
    if failed:
        print("%s: findings in %d of %d files (above); %s" % (check.name, failed, len(files), check.advice),
              file=sys.stderr)
        return 1
    tool.touch()
    print("%s: %d files, no findings (%d unchanged since a passing run)" % (check.name, len(files), cached))
    return 0


if __name__ == "__main__":
    sys.exit(main())
