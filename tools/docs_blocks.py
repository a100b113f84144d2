#!/usr/bin/env python3
"""Check every code block of README.md and the guide (docs/**/*.md).

Run from the repository root after `cargo build` (tools/check.sh's `docs` stage
does both; standard library only):

    python3 tools/docs_blocks.py [--no-run] [--keep] [FILE.md ...]

What each kind of block gets:

- ```rust: compiled (and run, unless `no_run`) as doctests by `cargo test --doc`, through the
  `#[cfg(doctest)]` module of src/lib.rs; this script only checks that every page with a Rust
  block is listed there.
- ```c and ```cpp: compiled with -Wall -Wextra -Werror against include/flame.h (and
  bindings/cpp/flame.hpp) and linked with target/debug/libflame.so. A block that is not a whole
  program is marked `<!-- fragment -->` and compiled as the body of a function whose parameters
  are `FlameModel *model`, `FlameSession *session` and `FlameStream *stream`. A block marked
  `<!-- run ... -->` is also run (see below).
- ```sh (also bash, shell): `bash -n` (syntax) for all; run with `bash -e` when marked
  `<!-- run ... -->`, or marked `<!-- not run: REASON -->` (a reason is required).
- ```python: compiled (syntax); never run here, so it needs `<!-- not run: REASON -->`.
- ```json: parsed.
- ```text (output, usage synopses): not checked.
- any other language (cmake, ...): needs `<!-- not run: REASON -->`.

The marker is an HTML comment on the lines right before the fence (blank lines allowed between).
`<!-- run: NAME=PATH $VAR=PATH ... -->` runs the block in a scratch folder of its page
(target/docs-blocks/PAGE/, made afresh; the blocks of a page run in order and share it, so a
block may use what an earlier one wrote), with NAME a symbolic link to the repository's PATH
(a test fixture standing in for a converted checkpoint), $VAR=PATH an environment variable set to
the repository's PATH, and target/debug first on PATH (the `flame` CLI as built by cargo).

Pages written before the guide keep their shell blocks unmarked: LEGACY_NOT_RUN gives the
reason they are not run; their untagged blocks are shell commands and get `bash -n`. In every
other page, an untagged block is an error.

Exit status 1 when any block fails; each failure is printed as `file:line: message`.
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TARGET = os.environ.get("CARGO_TARGET_DIR") or os.path.join(ROOT, "target")
BIN_DIR = os.path.join(TARGET, "debug")
SCRATCH = os.path.join(TARGET, "docs-blocks")

# Pages the guide took in as they were: why their shell blocks are not run here.
LEGACY_NOT_RUN = {
    "docs/amass.md": "uses the demo model tools/try.sh assembles; tests/amass_export.rs and "
    "tests/robot_export.rs run the export on the fixtures",
    "docs/demo_corpus.md": "a usage synopsis; crates/flame-demo's tests run the corpus generator",
    "docs/demo_training.md": "trains the demo model (hours, PyTorch)",
    "docs/fuzzing.md": "needs cargo-fuzz; the fuzz stage of tools/check.sh runs tools/fuzz.sh",
    "docs/model-files-finemogen.md": "needs PyTorch and the official checkpoint",
    "docs/model-files-latent.md": "needs PyTorch and the official checkpoints",
    "docs/omg.md": "needs PyTorch (conversion and training)",
    "docs/performance.md": "benchmarks: minutes each, with PyTorch and ONNX Runtime",
    "docs/retargeting.md": "uses the demo model and the user's rigs; the retarget stage of "
    "tools/check.sh (tools/retarget_check.sh) runs the same commands on committed rigs",
}

FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([^`]*)$")
SHELLS = {"sh", "bash", "shell"}

FRAGMENT_PRELUDE = {
    "c": "#include <stdint.h>\n#include <stdio.h>\n#include <stdlib.h>\n#include <string.h>\n"
    "#include <flame.h>\n",
    "cpp": "#include <cstdint>\n#include <cstdio>\n#include <cstdlib>\n#include <string>\n"
    "#include <vector>\n#include \"flame.hpp\"\n",
}


class Block:
    def __init__(self, path, line, lang, attrs, text, marker):
        self.path, self.line, self.lang, self.attrs = path, line, lang, attrs
        self.text, self.marker = text, marker

    def where(self):
        return f"{self.path}:{self.line}"


def marker_before(lines, i):
    """The HTML comment right before line i (blank lines allowed between), or None."""
    j = i - 1
    while j >= 0 and not lines[j].strip():
        j -= 1
    if j < 0 or not lines[j].rstrip().endswith("-->"):
        return None
    k = j
    while k >= 0 and "<!--" not in lines[k]:
        k -= 1
    if k < 0:
        return None
    text = " ".join(l.strip() for l in lines[k : j + 1])
    return text[text.index("<!--") + 4 : text.rindex("-->")].strip()


def blocks_of(path):
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        lines = f.read().split("\n")
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, info = m.group(1), m.group(2), m.group(3).strip()
        tokens = [t for t in re.split(r"[,\s]+", info) if t]
        lang = tokens[0] if tokens else ""
        body, j = [], i + 1
        while j < len(lines):
            close = lines[j].strip()
            if close.startswith(fence[0] * len(fence)) and not close.strip(fence[0]):
                break
            body.append(lines[j][len(indent) :] if lines[j].startswith(indent) else lines[j])
            j += 1
        out.append(Block(path, i + 1, lang, tokens[1:], "\n".join(body) + "\n", marker_before(lines, i)))
        i = j + 1
    return out


def pages(args):
    if args:
        return args
    found = ["README.md"]
    for d, _, files in os.walk(os.path.join(ROOT, "docs")):
        for f in files:
            if f.endswith(".md"):
                found.append(os.path.relpath(os.path.join(d, f), ROOT))
    return sorted(found)


def parse_run(marker):
    """(symlinks, env) of a `run` marker."""
    links, env = {}, {}
    rest = marker[len("run") :].lstrip(":").split()
    for tok in rest:
        name, _, target = tok.partition("=")
        if not target:
            raise ValueError(f"`{tok}` in the run marker is not NAME=PATH")
        if name.startswith("$"):
            env[name[1:]] = os.path.join(ROOT, target)
        else:
            links[name] = os.path.join(ROOT, target)
    return links, env


def prepare(sandbox, links):
    for name, target in links.items():
        if not os.path.exists(target):
            raise ValueError(f"{target} does not exist")
        dest = os.path.join(sandbox, name)
        if os.path.lexists(dest):
            os.remove(dest)
        os.symlink(target, dest)


def run(cmd, cwd, env=None, timeout=300):
    e = dict(os.environ)
    e["PATH"] = BIN_DIR + os.pathsep + e.get("PATH", "")
    e.pop("FLAME_MODEL", None)
    e.update(env or {})
    try:
        p = subprocess.run(cmd, cwd=cwd, env=e, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return 1, f"timed out after {timeout} s"
    return p.returncode, p.stdout + p.stderr


class Checker:
    def __init__(self, no_run):
        self.no_run = no_run
        self.failures = []
        self.counts = {}
        self.sandboxes = {}
        self.doctest_pages = self.doctest_pages_of_lib()

    def fail(self, block, msg):
        self.failures.append(f"{block.where()}: {msg}")

    def count(self, kind, how):
        self.counts.setdefault(kind, {}).setdefault(how, 0)
        self.counts[kind][how] += 1

    @staticmethod
    def doctest_pages_of_lib():
        with open(os.path.join(ROOT, "src", "lib.rs"), encoding="utf-8") as f:
            text = f.read()
        return {os.path.normpath(os.path.join("src", p)) for p in re.findall(r'"(\.\./[^"]+\.md)"', text)}

    def sandbox(self, page):
        if page not in self.sandboxes:
            d = os.path.join(SCRATCH, re.sub(r"[^\w.-]", "_", page))
            shutil.rmtree(d, ignore_errors=True)
            os.makedirs(d)
            self.sandboxes[page] = d
        return self.sandboxes[page]

    def check(self, b):
        marker = b.marker or ""
        not_run = marker.startswith("not run")
        if not_run and not marker.partition(":")[2].strip():
            self.fail(b, "`not run` needs a reason: <!-- not run: REASON -->")
            return
        wants_run = marker == "run" or marker.startswith("run:")
        lang = b.lang
        if lang == "" and b.path in LEGACY_NOT_RUN:
            lang = "sh"
        if lang == "rust":
            if b.path not in self.doctest_pages:
                self.fail(b, f"a Rust block in a page that src/lib.rs's doctest module does not include "
                          f"(add it to `mod guide`)")
            else:
                self.count("rust", "doctest (cargo test --doc)" if "no_run" not in b.attrs else "doctest, compiled only (no_run)")
        elif lang in ("c", "cpp"):
            self.check_c(b, lang, wants_run and not self.no_run)
        elif lang in SHELLS:
            self.check_sh(b, marker, wants_run, not_run)
        elif lang == "python":
            try:
                compile(b.text, b.where(), "exec")
            except SyntaxError as e:
                self.fail(b, f"python syntax: {e}")
                return
            if not not_run:
                self.fail(b, "python blocks are not run here: mark <!-- not run: REASON -->")
                return
            self.count("python", "syntax-checked, not run")
        elif lang == "json":
            try:
                json.loads(b.text)
            except ValueError as e:
                self.fail(b, f"json: {e}")
                return
            self.count("json", "parsed")
        elif lang == "text":
            self.count("text", "not checked")
        elif lang == "":
            self.fail(b, "a code block without a language (```sh, ```rust, ```c, ```text, ...)")
        elif not_run:
            self.count(lang, "not run")
        else:
            self.fail(b, f"no check for ```{lang} blocks: mark <!-- not run: REASON -->")

    def check_sh(self, b, marker, wants_run, not_run):
        p = subprocess.run(["bash", "-n"], input=b.text, capture_output=True, text=True)
        if p.returncode != 0:
            self.fail(b, f"bash -n: {p.stderr.strip()}")
            return
        if wants_run:
            if self.no_run:
                self.count("sh", "syntax-checked (--no-run)")
                return
            try:
                links, env = parse_run(marker)
                box = self.sandbox(b.path)
                prepare(box, links)
            except ValueError as e:
                self.fail(b, str(e))
                return
            start = time.monotonic()
            code, out = run(["bash", "-e", "-c", b.text], box, env)
            if code != 0:
                self.fail(b, f"exit status {code}:\n{out[-3000:]}")
                return
            self.count("sh", "run")
            print(f"  ran {b.where()} in {time.monotonic() - start:.1f} s")
        elif not_run:
            self.count("sh", "syntax-checked, not run (reason given)")
        elif b.path in LEGACY_NOT_RUN:
            self.count("sh", "syntax-checked, not run (page's reason)")
        else:
            self.fail(b, "shell block: mark <!-- run ... --> or <!-- not run: REASON -->")

    def check_c(self, b, lang, do_run):
        fragment = (b.marker or "").startswith("fragment")
        ext = ".c" if lang == "c" else ".cpp"
        build = os.path.join(SCRATCH, "build")
        os.makedirs(build, exist_ok=True)
        stem = re.sub(r"[^\w]", "_", b.path) + f"_{b.line}"
        src = os.path.join(build, stem + ext)
        exe = os.path.join(build, stem)
        with open(src, "w", encoding="utf-8") as f:
            f.write(f'#line 1 "{b.path}:{b.line}"\n' if not fragment else "")
            if fragment:
                f.write(FRAGMENT_PRELUDE[lang])
                f.write("void docs_fragment(FlameModel *model, FlameSession *session, FlameStream *stream);\n")
                f.write("void docs_fragment(FlameModel *model, FlameSession *session, FlameStream *stream) {\n")
                f.write("    (void)model; (void)session; (void)stream;\n")
                f.write(f'#line 1 "{b.path}:{b.line}"\n')
                f.write(b.text)
                f.write("}\nint main(void) { return 0; }\n")
            else:
                f.write(b.text)
        if lang == "c":
            cmd = [os.environ.get("CC", "gcc"), "-std=c11"]
        else:
            cmd = [os.environ.get("CXX", "g++"), "-std=c++17", "-I", os.path.join(ROOT, "bindings", "cpp")]
        cmd += ["-Wall", "-Wextra", "-Werror", "-I", os.path.join(ROOT, "include"), src,
                "-L", BIN_DIR, "-lflame", f"-Wl,-rpath,{BIN_DIR}", "-o", exe]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            self.fail(b, f"does not compile and link:\n{p.stderr[-3000:]}")
            return
        kind = "fragment compiled" if fragment else "compiled and linked"
        if do_run and not fragment:
            try:
                links, env = parse_run(b.marker)
                box = self.sandbox(b.path)
                prepare(box, links)
            except ValueError as e:
                self.fail(b, str(e))
                return
            code, out = run([exe], box, env)
            if code != 0:
                self.fail(b, f"ran with exit status {code}:\n{out[-3000:]}")
                return
            kind = "compiled, linked and run"
        self.count(lang, kind)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="*", help="pages (default: README.md and docs/**/*.md)")
    ap.add_argument("--no-run", action="store_true", help="compile and syntax-check only")
    args = ap.parse_args()
    os.chdir(ROOT)
    for need in ("flame", "libflame.so"):
        if not os.path.exists(os.path.join(BIN_DIR, need)):
            print(f"docs_blocks: {os.path.join(BIN_DIR, need)} is missing: run "
                  "`cargo build` first", file=sys.stderr)
            return 1
    checker = Checker(args.no_run)
    total = 0
    for page in pages(args.files):
        for b in blocks_of(page):
            total += 1
            checker.check(b)
    for kind in sorted(checker.counts):
        hows = ", ".join(f"{n} {how}" for how, n in sorted(checker.counts[kind].items()))
        print(f"docs_blocks: {kind}: {hows}")
    for f in checker.failures:
        print(f)
    print(f"docs_blocks: {total} code blocks, {len(checker.failures)} failing")
    return 1 if checker.failures else 0


if __name__ == "__main__":
    sys.exit(main())
