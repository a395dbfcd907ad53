#!/usr/bin/env bash
# Checks the documentation (scripts/test.sh runs it after the tests):
#   (a) every `vernier …` command shown in a shell code block of README.md, CHANGELOG.md,
#       examples/README.md and docs/**/*.md runs and exits 0, against the built CLI, in a
#       scratch folder laid out like the repository: a copy of examples/, and ../shared/data
#       linked to $VERNIER_DATA_DIR (default ../shared/data). A block preceded by an HTML
#       comment `<!-- no-run … -->` is skipped (ROS, cameras, long runs, files written into
#       the repository); a block preceded by `<!-- run -->` runs every line, not only the
#       `vernier` ones. Commands of one file share one scratch folder, in order.
#   (b) every relative link and #anchor in those files and launch_scripts/README.md resolves
#       (files exist; anchors are headings' GitHub slugs or explicit <a id="…">), and so does
#       every `docs/design.md#anchor` the Rust sources and params/detector.yaml cite;
#   (c) the API docs build without warnings: RUSTDOCFLAGS="-D warnings" cargo doc --no-deps
#       --workspace --locked (CHECK_DOCS_SKIP_RUSTDOC=1 skips it).
# The CLI: $VERNIER if set; else target/debug/vernier when `cargo test` has built it and it is
# newer than the sources; else `cargo build --release -p vernier-cli --locked`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
data="${VERNIER_DATA_DIR:-$root/../shared/data}"
[ -d "$data" ] || { echo "check_docs: test data not found at $data (set VERNIER_DATA_DIR)" >&2; exit 1; }
data="$(cd "$data" && pwd)"

if [ -z "${VERNIER:-}" ]; then
    target_dir="$(cargo metadata --format-version 1 --no-deps --locked |
        grep -o '"target_directory":"[^"]*"' | cut -d'"' -f4)"
    VERNIER="$target_dir/debug/vernier"
    newest_source="$(find vernier/src vernier-cli/src -name '*.rs' -newer "$VERNIER" 2>/dev/null | head -1 || true)"
    if [ ! -x "$VERNIER" ] || [ -n "$newest_source" ]; then
        echo "== check_docs: building the release CLI"
        cargo build --release -p vernier-cli --locked --quiet
        VERNIER="$target_dir/release/vernier"
    fi
fi
VERNIER="$(cd "$(dirname "$VERNIER")" && pwd)/$(basename "$VERNIER")"
[ -x "$VERNIER" ] || { echo "check_docs: no vernier binary at $VERNIER" >&2; exit 1; }
echo "== docs: commands (with $VERNIER), links and anchors"

scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
mkdir -p "$scratch/bin" "$scratch/shared"
ln -s "$VERNIER" "$scratch/bin/vernier"
ln -s "$data" "$scratch/shared/data"

python3 - "$root" "$scratch" <<'PY'
import os
import re
import subprocess
import sys
import time

root, scratch = sys.argv[1], sys.argv[2]
os.chdir(root)

RUN_FILES = ["README.md", "CHANGELOG.md", "examples/README.md"]
LINK_FILES = RUN_FILES + ["launch_scripts/README.md"]
for folder, _, names in sorted(os.walk("docs")):
    for name in sorted(names):
        if name.endswith(".md"):
            path = os.path.join(folder, name)
            RUN_FILES.append(path)
            LINK_FILES.append(path)
RUN_FILES = [f for f in RUN_FILES if os.path.exists(f)]
LINK_FILES = [f for f in dict.fromkeys(LINK_FILES) if os.path.exists(f)]

FENCE = re.compile(r"^(\s*)(```+|~~~+)\s*([\w+-]*)")
SHELL = {"sh", "bash", "shell", "console"}
VERNIER_LINE = re.compile(r"^(?:[A-Z_][A-Z0-9_]*=\S*\s+)*vernier\s")
failures = []


def blocks(path):
    """(first line number, language, lines, marker) of each fenced block; marker is the HTML
    comment right before it ('no-run', 'run' or None)."""
    lines = open(path, encoding="utf-8").read().split("\n")
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang = m.group(2), m.group(3).lower()
        marker = None
        j = i - 1
        while j >= 0 and lines[j].strip() == "":
            j -= 1
        if j >= 0:
            c = re.match(r"\s*<!--\s*(no-run|run)\b", lines[j])
            if c:
                marker = c.group(1)
        body, k = [], i + 1
        while k < len(lines) and not lines[k].strip().startswith(fence[:3]):
            body.append(lines[k])
            k += 1
        out.append((i + 2, lang, body, marker))
        i = k + 1
    return out


def commands(body, every_line):
    """Shell commands of a block, continuation lines joined, with their line offsets."""
    cmds, current, start = [], "", 0
    for n, line in enumerate(body):
        if not current:
            start = n
        stripped = line.rstrip()
        if stripped.endswith("\\"):
            current += stripped[:-1] + " "
            continue
        current += stripped
        text = current.strip()
        current = ""
        if not text or text.startswith("#"):
            continue
        if every_line or VERNIER_LINE.match(text):
            cmds.append((start, text))
    return cmds


# (a) commands
env = dict(os.environ)
env["PATH"] = os.path.join(scratch, "bin") + os.pathsep + env["PATH"]
env["VERNIER_DATA_DIR"] = os.path.join(scratch, "shared", "data")
ran = skipped = 0
started = time.time()
for n_file, path in enumerate(RUN_FILES):
    work = os.path.join(scratch, f"work{n_file}", "repo")
    os.makedirs(work)
    os.symlink(os.path.join(scratch, "shared"), os.path.join(scratch, f"work{n_file}", "shared"))
    subprocess.run(["cp", "-r", os.path.join(root, "examples"), work], check=True)
    for line_no, lang, body, marker in blocks(path):
        if lang not in SHELL:
            continue
        cmds = commands(body, marker == "run")
        if marker == "no-run":
            skipped += len(cmds)
            continue
        for offset, cmd in cmds:
            ran += 1
            try:
                r = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], cwd=work, env=env,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                   text=True, timeout=300)
                ok, err = r.returncode == 0, r.stderr
            except subprocess.TimeoutExpired:
                ok, err = False, "timed out after 300 s"
            if not ok:
                failures.append(f"{path}:{line_no + offset}: command failed: {cmd}\n"
                                + "\n".join("    " + l for l in err.strip().splitlines()[-5:]))
print(f"   {ran} commands run ({skipped} in no-run blocks skipped) in {time.time() - started:.0f} s")


# (b) links and anchors
def slug(heading):
    text = re.sub(r"<[^>]+>", "", heading)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


anchor_cache = {}


def anchors(path):
    if path not in anchor_cache:
        found, seen = set(), {}
        in_fence = False
        for line in open(path, encoding="utf-8"):
            if FENCE.match(line):
                in_fence = not in_fence
                continue
            if in_fence:
                continue
            for a in re.findall(r"""<a\s+(?:id|name)=["']([^"']+)["']""", line):
                found.add(a)
            m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
            if m:
                s = slug(m.group(2))
                n = seen.get(s, 0)
                seen[s] = n + 1
                found.add(s if n == 0 else f"{s}-{n}")
        anchor_cache[path] = found
    return anchor_cache[path]


def check_target(source, target, where):
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
        return  # external: not checked here
    file_part, _, anchor = target.partition("#")
    path = os.path.normpath(os.path.join(os.path.dirname(source), file_part)) if file_part else source
    if not os.path.exists(path):
        failures.append(f"{where}: link to a missing file: {target}")
        return
    if anchor:
        if os.path.isdir(path) or not path.endswith(".md"):
            failures.append(f"{where}: anchor on a file that has none: {target}")
        elif anchor not in anchors(path):
            failures.append(f"{where}: no anchor #{anchor} in {path}")


links = 0
for path in LINK_FILES:
    text = open(path, encoding="utf-8").read()
    in_fence = False
    for n, line in enumerate(text.split("\n"), 1):
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        line = re.sub(r"`[^`]*`", "", line)
        for target in re.findall(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", line):
            links += 1
            check_target(path, target, f"{path}:{n}")
        for target in re.findall(r"^\s*\[[^\]]+\]:\s*(\S+)", line):
            links += 1
            check_target(path, target, f"{path}:{n}")

cited = 0
for folder, dirs, names in os.walk("."):
    dirs[:] = [d for d in dirs if d not in ("target", ".git", ".venv", "node_modules")]
    for name in names:
        if not (name.endswith(".rs") or name.endswith(".yaml")):
            continue
        path = os.path.join(folder, name)
        for n, line in enumerate(open(path, encoding="utf-8", errors="replace"), 1):
            for anchor in re.findall(r"docs/design\.md#([A-Za-z0-9_-]+)", line):
                cited += 1
                if anchor not in anchors("docs/design.md"):
                    failures.append(f"{path[2:]}:{n}: cites docs/design.md#{anchor}, which does not exist")
print(f"   {links} links in {len(LINK_FILES)} files, {cited} design anchors cited by the code")

if failures:
    print("\n".join(failures), file=sys.stderr)
    print(f"check_docs: {len(failures)} problem(s)", file=sys.stderr)
    sys.exit(1)
PY

if [ "${CHECK_DOCS_SKIP_RUSTDOC:-0}" = 1 ]; then
    echo "== docs: cargo doc skipped (CHECK_DOCS_SKIP_RUSTDOC=1)"
else
    echo "== docs: RUSTDOCFLAGS=\"-D warnings\" cargo doc --no-deps --workspace --locked"
    RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --workspace --locked --quiet
fi
echo "== docs: all checks passed"
