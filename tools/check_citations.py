#!/usr/bin/env python3
"""Check that the tree's citations resolve.

Run from the repository root (standard library only):

    python3 tools/check_citations.py [--skip PATH]...

It reads every file git tracks (binary files and anything under target/ are skipped) and fails on:

1. a citation of the private notes file that is not part of the repository (its file name, or
   the "<NAME> <section number>" form): cite the primary source and a page of docs/official/;
2. a repository path `docs/<...>.md`, optionally followed by `#anchor`, anywhere in a file (code
   comments included) whose file does not exist or whose anchor is not a heading of that page
   (a path written right after another repository's name, as in "owner/name docs/<page>.md", is that
   repository's and is not checked);
3. a relative Markdown link, in README.md or docs/**/*.md, to a `.md` file or an anchor that does
   not exist.

Anchors are computed the way mdBook and GitHub compute them: the heading's text without its
markup, lower-cased, whitespace turned into '-', other punctuation dropped, and '-1', '-2', ...
appended to repeated headings. Each failure is printed as `file:line: message`; the exit status is
1 when there is any.

`--skip PATH` (repeatable) leaves PATH out of the scan as a source of citations and links; links
pointing to it are still checked.
"""
import argparse
import os
import re
import subprocess
import sys

# Spelled in two pieces so that this file does not match its own patterns.
_NAME = "REFER" + "ENCE"
NOTES_FILE = re.compile(r"\b" + _NAME + r"\.md\b")
NOTES_SECTION = re.compile(r"\b" + _NAME + r"(?:'s)?(?:\.md)?\s+(?:sections?\s+)?\d")
NOTES_POSSESSIVE = re.compile(r"\b" + _NAME + r"'s\b")

# A repository-root path to a page under docs/, not the tail of a longer path.
DOCS_PATH = re.compile(r"(?<![\w/.\-])(docs/[\w./\-]*?\.md)(?:#([\w\-]+))?")
# Text right before such a path that names another GitHub repository ("YanjieZe/GMR docs/<page>.md"):
# the path is that repository's, not ours.
OTHER_REPO = re.compile(r"(?:^|[\s(\[,;])[\w.\-]+/[\w.\-]+[ \t]+`?$")
# Inline Markdown links and images: [text](target "title").
MD_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
ATX = re.compile(r"^ {0,3}(#{1,6})[ \t]+(.*?)[ \t]*$")
CUSTOM_ID = re.compile(r"\s*\{#([\w\-]+)[^}]*\}\s*$")
HTML_ID = re.compile(r"<a\s+[^>]*(?:name|id)\s*=\s*\"([^\"]+)\"", re.I)


def tracked_files():
    out = subprocess.run(["git", "ls-files", "-z"], check=True, capture_output=True).stdout
    return [p for p in out.decode("utf-8", "surrogateescape").split("\0") if p]


def read_text(path):
    """The file's text, or None for binaries and unreadable files."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def heading_text(raw):
    """The rendered text of a heading: inline code, links, images and emphasis unwrapped."""
    text = re.sub(r"[ \t]+#+$", "", raw)  # closing hashes
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags
    text = text.replace("`", "")
    text = text.replace("*", "")
    text = re.sub(r"(?<![\w])_+|_+(?![\w])", "", text)  # _emphasis_, not snake_case
    return text.strip()


def slug(text):
    out = []
    for ch in text:
        if ch.isalnum() or ch in "_-":
            out.append(ch.lower())
        elif ch.isspace():
            out.append("-")
    return "".join(out)


_anchor_cache = {}


def anchors_of(path):
    """The set of anchors a Markdown page defines."""
    if path in _anchor_cache:
        return _anchor_cache[path]
    text = read_text(path) or ""
    seen = {}
    found = set()
    in_fence = False
    prev = ""
    for line in text.splitlines():
        if FENCE.match(line):
            in_fence = not in_fence
            prev = ""
            continue
        if in_fence:
            continue
        for m in HTML_ID.finditer(line):
            found.add(m.group(1))
        raw = None
        m = ATX.match(line)
        if m:
            raw = m.group(2)
        elif prev.strip() and re.match(r"^ {0,3}=+\s*$", line):
            raw = prev.strip()  # setext level-1 heading
        prev = line
        if raw is None:
            continue
        custom = CUSTOM_ID.search(raw)
        if custom:
            found.add(custom.group(1))
            continue
        base = slug(heading_text(raw))
        n = seen.get(base, 0)
        seen[base] = n + 1
        found.add(base if n == 0 else f"{base}-{n}")
    _anchor_cache[path] = found
    return found


def check_target(page, anchor, failures, where):
    if not os.path.isfile(page):
        failures.append(f"{where}: {page} does not exist")
        return
    if anchor and anchor not in anchors_of(page):
        failures.append(f"{where}: {page} has no heading with anchor #{anchor}")


def code_spans_blanked(line):
    """The line with inline code spans replaced by spaces (Markdown link checks skip code)."""
    return re.sub(r"`+[^`]*`+", lambda m: " " * len(m.group(0)), line)


def check_file(path, text, failures):
    is_md_doc = path.endswith(".md") and (path == "README.md" or path.startswith("docs/"))
    in_fence = False
    for no, line in enumerate(text.splitlines(), 1):
        where = f"{path}:{no}"
        if NOTES_FILE.search(line) or NOTES_SECTION.search(line) or NOTES_POSSESSIVE.search(line):
            failures.append(f"{where}: cites the private notes file; cite the primary source "
                            "and a docs/official/ page instead")
        for m in DOCS_PATH.finditer(line):
            if OTHER_REPO.search(line[:m.start()]):
                continue
            check_target(os.path.normpath(m.group(1)), m.group(2), failures, where)
        if not is_md_doc:
            continue
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        for m in MD_LINK.finditer(code_spans_blanked(line)):
            target = m.group(1)
            if re.match(r"^[a-zA-Z][a-zA-Z0-9+.\-]*:", target) or target.startswith("/"):
                continue  # a URL (http:, mailto:, ...) or a site-absolute path
            page, _, anchor = target.partition("#")
            if not page:
                check_target(path, anchor, failures, where)
                continue
            if not page.endswith(".md"):
                continue
            resolved = os.path.normpath(os.path.join(os.path.dirname(path), page))
            check_target(resolved, anchor, failures, where)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--skip", action="append", default=[], metavar="PATH",
                    help="a tracked file (repository-relative) not to scan; repeatable")
    args = ap.parse_args(argv)
    skip = {os.path.normpath(p) for p in args.skip}
    failures = []
    for path in tracked_files():
        if path.startswith("target/") or "/target/" in path or os.path.normpath(path) in skip:
            continue
        text = read_text(path)
        if text is None:
            continue
        check_file(path, text, failures)
    for f in failures:
        print(f)
    if failures:
        print(f"{len(failures)} citation problem(s)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
