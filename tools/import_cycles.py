#!/usr/bin/env python3
"""Import graph between the Rust files of this workspace, and its cycles.

An edge a.rs -> b.rs is a `use crate::...`/`super::...`/`kfmap_x::...` path in a.rs
that resolves to the module file b.rs. Edges between a module and its own ancestors
(mod.rs declaring a child and the child using its parent's items) are left out: they
are nesting, not a cycle between concerns. Prints every strongly connected component
of more than one file; `--edges` also prints the graph. Exit 1 when a cycle exists.
"""
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def crates():
    """(crate ident, src dir) of every workspace member with a lib or bin."""
    found = {}
    for dirpath, dirnames, files in os.walk(ROOT):
        dirnames[:] = [d for d in dirnames if d not in ("target", ".git", "fuzz", "python", "node_modules")]
        if "Cargo.toml" in files and os.path.isdir(os.path.join(dirpath, "src")):
            text = open(os.path.join(dirpath, "Cargo.toml")).read()
            m = re.search(r'^name\s*=\s*"([^"]+)"', text, re.M)
            if m:
                found[m.group(1).replace("-", "_")] = os.path.join(dirpath, "src")
    return found


def module_files(src):
    """Module path (tuple) -> file, for every .rs file under src."""
    mods = {}
    for dirpath, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs"):
                continue
            rel = os.path.relpath(os.path.join(dirpath, f), src)[:-3].split(os.sep)
            if rel[-1] in ("mod", "lib", "main"):
                rel = rel[:-1]
            mods[tuple(rel)] = os.path.join(dirpath, f)
    return mods


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


PATH = re.compile(r"\b((?:crate|super|self|[a-z_][a-z0-9_]*)(?:::(?:[a-z_][a-z0-9_]*|\{))+)")


def main():
    all_crates = crates()
    graph = {}
    for ident, src in all_crates.items():
        mods = module_files(src)
        for mod, path in mods.items():
            here = list(mod)
            # A file that is not mod.rs/lib.rs is its own module; `super` is its parent.
            text = strip_comments(open(path).read())
            for m in PATH.finditer(text):
                parts = m.group(1).split("::")
                if parts[-1] == "{":
                    parts = parts[:-1]
                if parts[0] == "crate":
                    target_crate, base = ident, []
                    rest = parts[1:]
                elif parts[0] in ("super", "self"):
                    base = list(here)
                    rest = parts
                    while rest and rest[0] in ("super", "self"):
                        if rest[0] == "super" and base:
                            base = base[:-1]
                        rest = rest[1:]
                    target_crate = ident
                elif parts[0] in all_crates:
                    target_crate, base, rest = parts[0], [], parts[1:]
                else:
                    continue
                tmods = module_files(all_crates[target_crate]) if target_crate != ident else mods
                full = base + rest
                # Longest prefix that names a module file.
                for n in range(len(full), -1, -1):
                    key = tuple(full[:n])
                    if key in tmods:
                        target = tmods[key]
                        break
                else:
                    continue
                if target == path:
                    continue
                if target_crate == ident:
                    tkey = key
                    if tkey == tuple(here[: len(tkey)]) or tuple(here) == tkey[: len(here)]:
                        continue  # ancestor or descendant: nesting
                graph.setdefault(path, set()).add(target)
    # Tarjan's strongly connected components.
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]
    sys.setrecursionlimit(100000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
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
            if len(comp) > 1:
                comps.append(comp)

    for v in list(graph):
        if v not in index:
            visit(v)
    rel = lambda p: os.path.relpath(p, ROOT)
    if "--edges" in sys.argv:
        for a in sorted(graph):
            print(rel(a), "->", ", ".join(sorted(rel(b) for b in graph[a])))
    files = {p for p in graph} | {q for s in graph.values() for q in s}
    edges = sum(len(s) for s in graph.values())
    print(f"{len(files)} files, {edges} import edges between them, {len(comps)} cycles")
    for c in comps:
        print("cycle:", " <-> ".join(sorted(rel(p) for p in c)))
    sys.exit(1 if comps else 0)


main()
