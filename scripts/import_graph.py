#!/usr/bin/env python3
"""The import graph of gdrf-core: which source file imports which, and what points back up.

    scripts/import_graph.py [--json OUT] [--edges]

A node is one source file of gdrf-core/src (a module); an edge A -> B says that A names an
item of B (`use crate::b::...`, `super::b::...`, a child `use b::...`, or an inline
`crate::b::f(...)` path). Rooms are the top-level modules (`render`, `data`, ...); their order
from the foundations up is ROOMS below, the order ARCHITECTURE.md draws. An edge points back
up when it goes from a room to a later room in that order. Circles are strongly connected
groups of files. Prints the counts, the back edges and the circles; --json writes them too.
"""
import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "gdrf-core" / "src"

# The rooms from the bottom up: each may import only rooms before it. A room missing from
# the tree is skipped; a room in the tree missing here is an error (add it where it belongs).
ROOMS = [
    "error", "paths", "rng", "stats", "progress", "device", "dist", "io", "plot", "config", "nn", "camera", "pretrained",
    "field", "render", "checkpoint", "data", "disc", "loss", "mesh", "edit", "eval", "train",
    "invert", "bench",
]


def module_of(path: Path) -> tuple[str, ...]:
    rel = path.relative_to(SRC).with_suffix("")
    parts = rel.parts
    if parts[-1] in ("mod", "lib"):
        parts = parts[:-1]
    return tuple(parts)


def strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    return re.sub(r"//[^\n]*", "", text)


def expand(tree: str) -> list[str]:
    """`a::{b, c::{d, e}}` -> [a::b, a::c::d, a::c::e]."""
    tree = tree.strip()
    i = tree.find("{")
    if i < 0:
        return [tree.split(" as ")[0].strip()]
    prefix, inner = tree[:i], tree[i + 1:tree.rfind("}")]
    items, depth, cur = [], 0, ""
    for ch in inner:
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
            continue
        depth += ch == "{"
        depth -= ch == "}"
        cur += ch
    items.append(cur)
    out = []
    for item in items:
        if item.strip():
            out += [prefix + p if p != "self" else prefix.rstrip(":") for p in expand(item)]
    return out


def paths_in(text: str) -> list[str]:
    paths = []
    for m in re.finditer(r"\buse\s+([^;]+);", text):
        paths += expand(m.group(1))
    # Inline paths outside use statements.
    body = re.sub(r"\buse\s+[^;]+;", "", text)
    paths += re.findall(r"\b((?:crate|super)(?:::[A-Za-z_][A-Za-z0-9_]*)+)", body)
    return [re.sub(r"\s+", "", p) for p in paths]


def resolve(path: str, me: tuple[str, ...], is_dir: bool, modules: set) -> tuple[str, ...] | None:
    segs = path.split("::")
    if segs[0] == "crate":
        base, rest = (), segs[1:]
    elif segs[0] == "super":
        base = me
        while segs and segs[0] == "super":
            base = base[:-1]
            segs = segs[1:]
        rest = segs
    elif segs[0] == "self":
        base, rest = me, segs[1:]
    elif is_dir and me + (segs[0],) in modules:
        base, rest = me, segs  # a child module named in its parent's `use`
    else:
        return None
    best = base if base in modules else None
    for k in range(1, len(rest) + 1):
        if base + tuple(rest[:k]) in modules:
            best = base + tuple(rest[:k])
    return best


def graph():
    files = sorted(SRC.rglob("*.rs"))
    modules = {module_of(f): f for f in files}
    edges = set()
    for mod, f in modules.items():
        text = strip_comments(f.read_text())
        # Test modules inside a file do not count: they may import what they test from.
        text = re.split(r"#\[cfg\(test\)\]", text)[0]
        is_dir = f.name in ("mod.rs", "lib.rs")
        for p in paths_in(text):
            target = resolve(p, mod, is_dir, set(modules))
            if target is None or target == mod or target == ():
                continue
            # A parent naming its own descendants' items (re-exports, `mod` facades) is the
            # module tree itself, not an import between layers.
            if target[: len(mod)] == mod:
                continue
            edges.add((mod, target))
    return modules, edges


def room(mod):
    return mod[0] if mod else "lib"


def sccs(nodes, edges):
    adj = {n: [] for n in nodes}
    for a, b in edges:
        adj[a].append(b)
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in adj[v]:
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
                out.append(sorted(comp))

    for n in nodes:
        if n not in index:
            visit(n)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--edges", action="store_true", help="print every edge")
    args = ap.parse_args()
    modules, edges = graph()
    rooms = sorted({room(m) for m in modules if m})
    unknown = [r for r in rooms if r not in ROOMS]
    if unknown:
        sys.exit(f"import_graph: rooms missing from ROOMS: {unknown}")
    order = {r: i for i, r in enumerate(ROOMS)}
    name = lambda m: "::".join(m) or "lib"
    back = sorted(
        (name(a), name(b)) for a, b in edges if a and b and order[room(b)] > order[room(a)]
    )
    circles = [[name(m) for m in c] for c in sccs(list(modules), edges)]
    room_edges = {(room(a), room(b)) for a, b in edges if a and b and room(a) != room(b)}
    rust = lambda d: sum(len(p.read_text().splitlines()) for p in (ROOT / d).rglob("*.rs"))
    core_lines = rust("gdrf-core/src")
    bin_lines = sum(rust(f"{b}/src") for b in ("gdrf-train", "gdrf-edit", "gdrf-invert"))
    largest = sorted(((len(f.read_text().splitlines()), str(f.relative_to(ROOT))) for f in
                      ROOT.glob("gdrf-*/src/**/*.rs")), reverse=True)[:8]
    report = {
        "modules": len(modules) - 1,
        "rooms": len(rooms),
        "edges": len([e for e in edges if e[0]]),
        "room_edges": len(room_edges),
        "back_edges": back,
        "circles": circles,
        "core_lines": core_lines,
        "binary_lines": bin_lines,
        "binary_share": round(bin_lines / (core_lines + bin_lines), 3),
        "largest_files": [{"lines": n, "file": f} for n, f in largest],
    }
    print(f"{report['modules']} modules in {report['rooms']} rooms, {report['edges']} import edges "
          f"({report['room_edges']} between rooms), {len(back)} pointing back up, "
          f"{len(circles)} circles")
    print(f"binaries: {bin_lines} of {core_lines + bin_lines} Rust lines "
          f"({100 * report['binary_share']:.1f} %)")
    for a, b in back:
        print(f"  back: {a} -> {b}")
    for c in circles:
        print(f"  circle: {' <-> '.join(c)}")
    for item in largest:
        print(f"  {item[0]:5d} {item[1]}")
    if args.edges:
        for a, b in sorted(edges):
            print(f"  {name(a)} -> {name(b)}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
