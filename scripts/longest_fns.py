#!/usr/bin/env python3
"""List the longest Rust functions in production code (tests, examples and benches left out).

    python3 scripts/longest_fns.py [--most 15] [--rev REV]

A function's length is the number of lines from its `fn` line to its closing brace. Bodies
are matched by braces after removing comments, strings and char literals, so the count is
exact for ordinary code; `#[cfg(test)]` modules are skipped. With --rev the files are read
from that commit (git show), so two trees can be compared side by side.
"""
import argparse
import re
import subprocess
import sys

FN = re.compile(r"^\s*(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?(extern\s+\"[^\"]*\"\s+)?fn\s+(\w+)")
TOKENS = re.compile(r'//[^\n]*|/\*.*?\*/|r(#*)".*?"\1|b?"(?:\\.|[^"\\])*"|b?\'(?:\\.|[^\'\\])\'', re.S)


def blank(m):
    # Keep the line count: replace a comment or literal by its newlines only.
    return "\n" * m.group(0).count("\n")


def files(rev):
    cmd = ["git", "ls-files"] if rev is None else ["git", "ls-tree", "-r", "--name-only", rev]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.split()
    keep = []
    for f in out:
        if not f.endswith(".rs") or f.startswith(("tests/", "fuzz/")):
            continue
        if any(p in f for p in ("/tests/", "/examples/", "/benches/")):
            continue
        keep.append(f)
    return keep


def read(f, rev):
    if rev is None:
        return open(f, encoding="utf-8").read()
    return subprocess.run(["git", "show", f"{rev}:{f}"], capture_output=True, text=True,
                          check=True).stdout


def functions(path, text):
    code = TOKENS.sub(blank, text).split("\n")
    out, skip_to = [], -1
    for i, line in enumerate(code):
        if i <= skip_to:
            continue
        if line.strip().startswith("#[cfg(test)]"):
            # A test-only item: a module or function (to its brace), or a `use` (its line).
            end = close_of(code, i)
            skip_to = end if end is not None else i + 1
            continue
        m = FN.match(line)
        if not m:
            continue
        end = close_of(code, i)
        if end is not None and end > i:
            out.append((end - i + 1, f"{path}:{i + 1}", m.group(7)))
    return out


def close_of(code, start):
    """Index of the line whose `}` closes the first `{` at or after `start` (None for `;`)."""
    depth, opened = 0, False
    for j in range(start, len(code)):
        for ch in code[j]:
            if ch == "{":
                depth += 1
                opened = True
            elif ch == "}":
                depth -= 1
                if opened and depth == 0:
                    return j
            elif ch == ";" and not opened and depth == 0:
                return None
    return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--most", type=int, default=15)
    ap.add_argument("--rev")
    a = ap.parse_args()
    fns = []
    for f in files(a.rev):
        fns.extend(functions(f, read(f, a.rev)))
    fns.sort(reverse=True)
    over = sum(1 for n, _, _ in fns if n > 100)
    print(f"{len(fns)} functions; {over} longer than 100 lines")
    for n, where, name in fns[: a.most]:
        print(f"{n:5d}  {name}  {where}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
