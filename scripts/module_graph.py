#!/usr/bin/env python3
"""The module graph of one crate's src/*.rs (issue 39): prints it and its cycles.

Reads every `use crate::...` tree and every `crate::x` path of each top-level module
`src/<name>.rs`, in its code and in its doc comments (a doc link [`crate::x`] ties the
text to x's path as an import does; issue 39 counts them). Plain comments and string
literals are removed first. A path `crate::Name` where `Name` is re-exported by lib.rs
(`pub use module::{Name, ...}`) counts as an import of the module that defines it.
lib.rs itself (it re-exports everything) and main.rs are not nodes (main.rs is the root
of a crate without lib.rs).

  --code-only leave out doc-comment links ([`crate::x`])
  --no-tests  leave out `#[cfg(test)] mod tests { ... }` blocks

Exits 1 when the graph has a cycle (a strongly connected component of more than
one module, or a module importing itself), 0 otherwise.

Usage: scripts/module_graph.py [--code-only] [--no-tests] [SRC_DIR]
(default SRC_DIR: nodes/mesher/src beside this script's repository)
"""

import os
import re
import sys

IDENT = r"[A-Za-z_][A-Za-z0-9_]*"


def strip_code(text, keep_docs):
    """Blanks comments (all, or all but doc comments when keep_docs) and string/char
    literals, keeping offsets and newlines, so brace matching and paths see code only."""
    out = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            is_doc = text.startswith("///", i) or text.startswith("//!", i)
            if keep_docs and is_doc:
                out.append(text[i:j])
            else:
                out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "r" and re.match(r'r#*"', text[i:]) and not re.match(r"[A-Za-z0-9_]", text[i - 1] if i else " "):
            m = re.match(r'r(#*)"', text[i:])
            close = '"' + m.group(1)
            j = text.find(close, i + len(m.group(0)))
            j = n if j < 0 else j + len(close)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            j += 1
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "'":
            m = re.match(r"'(\\.[^']*|[^\\'])'", text[i:])
            if m:
                out.append(" " * len(m.group(0)))
                i += len(m.group(0))
            else:  # a lifetime
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


def blank_test_mods(code):
    """Blanks `#[cfg(test)] mod NAME { ... }` blocks."""
    for m in reversed(list(re.finditer(r"#\[cfg\(test\)\]\s*mod\s+" + IDENT + r"\s*\{", code))):
        depth, j = 0, m.end() - 1
        while j < len(code):
            if code[j] == "{":
                depth += 1
            elif code[j] == "}":
                depth -= 1
                if depth == 0:
                    break
            j += 1
        code = code[: m.start()] + re.sub(r"[^\n]", " ", code[m.start() : j + 1]) + code[j + 1 :]
    return code


def split_top(group):
    """Splits a use-tree group's body at its top-level commas."""
    parts, depth, cur = [], 0, []
    for c in group:
        if c == "{":
            depth += 1
        elif c == "}":
            depth -= 1
        if c == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
        else:
            cur.append(c)
    if "".join(cur).strip():
        parts.append("".join(cur).strip())
    return parts


def first_segments(tree):
    """The first path segments named by a use tree after `crate::`."""
    tree = re.sub(r"\s+", "", tree)
    if tree.startswith("{"):
        out = []
        for part in split_top(tree[1:-1]):
            out.extend(first_segments(part))
        return out
    m = re.match(IDENT, tree)
    return [m.group(0)] if m else []


def reexports(lib_code, modules):
    """name -> defining module, from lib.rs's `pub use module::...` lines."""
    found = {}
    for m in re.finditer(r"pub\s+use\s+(" + IDENT + r")::(\{[^;]*\}|" + IDENT + r")\s*;", lib_code):
        module, names = m.group(1), m.group(2)
        if module not in modules:
            continue
        body = names[1:-1] if names.startswith("{") else names
        for name in split_top(body):
            name = re.sub(r"\s+", "", name)
            if "::" in name or "{" in name:
                continue
            name = name.split("as")[0] if re.match(IDENT + "as" + IDENT + "$", name) else name
            found[name] = module
    return found


def resolve(seg, modules, reexp):
    if seg in modules:
        return seg
    if seg in reexp:
        return reexp[seg]
    return None


def edges_of(code, modules, reexp):
    """{target module: [the names through which it is reached]} for one file."""
    out = {}
    spans = []
    for m in re.finditer(r"\buse\s+crate::", code):
        end = code.find(";", m.end())
        spans.append((m.start(), end))
        for seg in first_segments(code[m.end() : end]):
            t = resolve(seg, modules, reexp)
            if t:
                out.setdefault(t, set()).add(seg)
    # `$crate::` is a macro_rules path: it names the crate root wherever the macro expands,
    # not an import of the module the macro is written in.
    for m in re.finditer(r"(?<!\$)\bcrate::(" + IDENT + ")", code):
        if any(a <= m.start() < b for a, b in spans):
            continue
        seg = m.group(1)
        t = resolve(seg, modules, reexp)
        if t:
            out.setdefault(t, set()).add(seg)
    return out


def sccs(graph):
    """Tarjan's strongly connected components, in a deterministic order."""
    index, low, on, stack, comps, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            comps.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comps


def layers(graph):
    """Longest-path layering of an acyclic graph: layer 0 imports nothing."""
    depth = {}

    def d(v):
        if v not in depth:
            depth[v] = 0
            depth[v] = 1 + max((d(w) for w in graph[v]), default=-1)
        return depth[v]

    for v in graph:
        d(v)
    by = {}
    for v, k in depth.items():
        by.setdefault(k, []).append(v)
    return [sorted(by[k]) for k in sorted(by)]


def main(argv):
    args = [a for a in argv if not a.startswith("--")]
    docs = "--code-only" not in argv
    no_tests = "--no-tests" in argv
    here = os.path.dirname(os.path.abspath(__file__))
    src = args[0] if args else os.path.join(here, "..", "nodes", "mesher", "src")
    files = sorted(f for f in os.listdir(src) if f.endswith(".rs"))
    modules = {f[:-3] for f in files} - {"lib", "main"}
    # A library's root is lib.rs; a binary-only crate's (the launcher) is main.rs.
    root = "lib.rs" if os.path.exists(os.path.join(src, "lib.rs")) else "main.rs"
    with open(os.path.join(src, root)) as fh:
        reexp = reexports(strip_code(fh.read(), False), modules)

    graph, via = {}, {}
    for f in files:
        name = f[:-3]
        if name not in modules:
            continue
        with open(os.path.join(src, f)) as fh:
            code = strip_code(fh.read(), docs)
        if no_tests:
            code = blank_test_mods(code)
        e = edges_of(code, modules, reexp)
        graph[name] = set(e)
        for t, names in e.items():
            via[(name, t)] = names

    print("module graph (%s%s):" % ("code and doc links" if docs else "code", ", no tests" if no_tests else ""))
    for v in sorted(graph):
        deps = []
        for t in sorted(graph[v]):
            names = sorted(n for n in via[(v, t)] if n != t)
            deps.append(t + ("(" + ",".join(names) + ")" if names else ""))
        print("  %-10s -> %s" % (v, " ".join(deps) if deps else "-"))

    cycles = [c for c in sccs(graph) if len(c) > 1 or c[0] in graph[c[0]]]
    if cycles:
        print("\ncycles (strongly connected components): %d" % len(cycles))
        for c in cycles:
            print("  {" + ", ".join(c) + "}")
            for v in c:
                inner = sorted(t for t in graph[v] if t in c)
                print("    %-10s -> %s" % (v, " ".join(inner)))
        return 1
    print("\nno cycles; layers (each imports only from layers before it):")
    for k, layer in enumerate(layers(graph)):
        print("  %d: %s" % (k, " ".join(layer)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
