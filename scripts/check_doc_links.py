#!/usr/bin/env python3
"""Check the relative links of the project's Markdown: every file a link names exists, and
every #anchor is a heading of the file it points into (GitHub's heading slugs).

    python3 scripts/check_doc_links.py              # README.md, docs/*.md, crate READMEs
    python3 scripts/check_doc_links.py FILE.md ...  # only these

Prints one line per broken link (file:line: target: why) and exits 1 when there is any;
web links (http:, https:, mailto:) are not followed. Run from the repository root.
"""
import glob
import os
import re
import sys

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def slug(heading):
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped (but - and _),
    spaces to hyphens."""
    text = re.sub(r"`([^`]*)`", r"\1", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def lines_outside_code(path):
    """(line number, text) of the lines not inside a fenced code block."""
    inside = False
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if FENCE.match(line):
                inside = not inside
                continue
            if not inside:
                yield number, line


def anchors(path, cache={}):
    if path not in cache:
        seen = {}
        found = set()
        for _, line in lines_outside_code(path):
            m = HEADING.match(line)
            if not m:
                continue
            base = slug(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
        cache[path] = found
    return cache[path]


def check(md):
    broken = []
    for number, line in lines_outside_code(md):
        line = re.sub(r"`[^`]*`", "", line)  # links inside code spans are not links
        for target in LINK.findall(line) + IMAGE.findall(line):
            if re.match(r"^[a-z]+:", target):
                continue
            file_part, _, anchor = target.partition("#")
            dest = os.path.normpath(os.path.join(os.path.dirname(md), file_part)) if file_part else md
            if not os.path.exists(dest):
                broken.append(f"{md}:{number}: {target}: no file {dest}")
                continue
            if anchor and dest.endswith(".md") and anchor not in anchors(dest):
                broken.append(f"{md}:{number}: {target}: no heading #{anchor} in {dest}")
    return broken


def main():
    files = sys.argv[1:] or sorted(
        ["README.md"]
        + glob.glob("docs/*.md")
        + glob.glob("common/*/README.md")
        + glob.glob("nodes/*/README.md")
        + glob.glob("launch/README.md")
        + glob.glob("python/README.md")
    )
    broken = [b for md in files for b in check(md)]
    for b in broken:
        print(b)
    total = sum(
        len(LINK.findall(re.sub(r"`[^`]*`", "", l))) + len(IMAGE.findall(l))
        for md in files
        for _, l in lines_outside_code(md)
    )
    print(f"{len(files)} files, {total} links, {len(broken)} broken", file=sys.stderr)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
