#!/usr/bin/env python3
"""Lists the `use` edges between the modules (files) of src/ and fails on an import cycle, or
on an edge against the layers of the ROS shell.

An edge A -> B means file A names an item of module B: in a `use` declaration or in a path
(`crate::x::y`, `super::y`, `self::y`). A name re-exported by a module (`pub use child::X` in
`core/mod.rs`) counts as an edge to the module that defines it, not to the one re-exporting
it; a module's own `pub use` of its children declares its interface and is not an edge. Test
code (`#[cfg(test)]` items and files under a `tests` module) is left out: it may reach
anything.

The layers of src/ros (see src/ros/mod.rs): interface < config < wire < inbound < outbound
< node.rs; a file may import only its own layer and the layers before it. safe_off.rs (the
tool that must work when the node is dead) may import nothing of src/ros above config.

Usage: scripts/check-layers.py [--edges]   (--edges prints every edge)
Exit status: 0 when there is no cycle and no layer is crossed, 1 otherwise.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"
LAYERS = ["interface", "config", "wire", "inbound", "outbound"]
#: Files that may import nothing of src/ros above this layer.
CEILINGS = {"safe_off": "config"}


def module_of(path: Path) -> tuple[str, ...]:
    rel = path.relative_to(SRC).with_suffix("")
    parts = rel.parts
    if parts[-1] in ("mod", "lib"):
        parts = parts[:-1]
    if parts == ("main",):
        return ("<main>",)
    return tuple(parts)


def strip_tests(text: str) -> str:
    """Removes comments, strings and `#[cfg(test)]` items (by brace matching)."""
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    out, i = [], 0
    for m in re.finditer(r"#\[cfg\(test\)\]", text):
        if m.start() < i:
            continue
        out.append(text[i : m.start()])
        j = m.end()
        # Skip the item: up to the end of its brace block or its semicolon.
        depth = 0
        while j < len(text):
            c = text[j]
            if c == "{":
                depth += 1
            elif c == "}":
                depth -= 1
                if depth == 0:
                    j += 1
                    break
            elif c == ";" and depth == 0:
                j += 1
                break
            j += 1
        i = j
    out.append(text[i:])
    return "".join(out)


def use_paths(text: str) -> list[tuple[str, bool]]:
    """Every path named (expanded `use` trees and inline paths), with whether it is `pub use`."""
    paths: list[tuple[str, bool]] = []

    def expand(prefix: str, tree: str) -> list[str]:
        tree = tree.strip()
        m = re.match(r"^(.*?)::\{(.*)\}$", tree, re.S)
        if m:
            base = (prefix + "::" if prefix else "") + m.group(1).strip()
            items, depth, cur = [], 0, ""
            for c in m.group(2):
                if c == "," and depth == 0:
                    items.append(cur)
                    cur = ""
                    continue
                depth += c == "{"
                depth -= c == "}"
                cur += c
            items.append(cur)
            result = []
            for it in items:
                if it.strip():
                    result += expand(base, it)
            return result
        tree = re.sub(r"\s+as\s+\w+$", "", tree)
        return [(prefix + "::" if prefix else "") + tree]

    for m in re.finditer(r"(pub(?:\([^)]*\))?\s+)?use\s+([^;]+);", text):
        for p in expand("", m.group(2)):
            paths.append((p.replace(" ", ""), bool(m.group(1))))
    body = re.sub(r"(pub(?:\([^)]*\))?\s+)?use\s+[^;]+;", "", text)
    for m in re.finditer(r"\b((?:crate|super|self)(?:::\w+)+)", body):
        paths.append((m.group(1), False))
    return paths


def resolve(path: str, here: tuple[str, ...], modules: set) -> tuple[str, ...] | None:
    """The module (file) a path names: the longest prefix of its absolute form that is one.
    `None` for a path outside the crate (std, other crates)."""
    parts = path.split("::")
    if parts[0] == "crate":
        base: list[str] = []
        parts = parts[1:]
    elif parts[0] == "self":
        base = list(here)
        parts = parts[1:]
    elif parts[0] == "super":
        base = list(here)
        while parts and parts[0] == "super":
            base = base[:-1]
            parts = parts[1:]
    else:
        return None
    full = base + parts
    for k in range(len(full), -1, -1):
        cand = tuple(full[:k])
        if cand in modules:
            return cand
    return ()


def main() -> int:
    files = sorted(SRC.rglob("*.rs"))
    modules: dict[tuple[str, ...], Path] = {}
    for f in files:
        if "tests" in f.relative_to(SRC).parts[:-1] or f.name == "tests.rs":
            continue
        modules[module_of(f)] = f
    modset = set(modules)
    texts = {m: strip_tests(p.read_text()) for m, p in modules.items()}

    # Re-exports: (module, name) -> defining module.
    reexports: dict[tuple[tuple[str, ...], str], tuple[str, ...]] = {}
    for m, text in texts.items():
        for p, public in use_paths(text):
            if not public:
                continue
            if not p.startswith(("crate", "super", "self")):
                p = "self::" + p
            target = resolve(p, m, modset)
            if target:
                reexports[(m, p.split("::")[-1])] = target

    edges: dict[tuple[str, ...], set[tuple[str, ...]]] = {m: set() for m in modules}
    for m, text in texts.items():
        for p, public in use_paths(text):
            if not p.startswith(("crate", "super", "self")):
                if public:
                    continue  # `pub use child::X`: the module's interface
                continue
            target = resolve(p, m, modset)
            if target is None:
                continue
            if public and target[: len(m)] == m:
                continue
            # Through a re-export to where the item is defined.
            name = p.split("::")[-1]
            seen = 0
            while (target, name) in reexports and seen < 10:
                target = reexports[(target, name)]
                seen += 1
            if target != m and target != ():
                edges[m].add(target)

    def show(m: tuple[str, ...]) -> str:
        return str(modules[m].relative_to(ROOT))

    if "--edges" in sys.argv:
        for m in sorted(edges):
            for t in sorted(edges[m]):
                print(f"{show(m)} -> {show(t)}")

    problems = []
    # Cycles (Tarjan's strongly connected components).
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
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
                sccs.append(comp)

    sys.setrecursionlimit(10000)
    for v in edges:
        if v not in index:
            strong(v)
    for comp in sccs:
        names = sorted(show(c) for c in comp)
        problems.append("import cycle among: " + ", ".join(names))

    def layer(m: tuple[str, ...]) -> int | None:
        if len(m) >= 2 and m[0] == "ros":
            if m[1] in LAYERS:
                return LAYERS.index(m[1])
            if m[1] == "node":
                return len(LAYERS)
        return None

    for m, targets in edges.items():
        lm = layer(m)
        for t in targets:
            lt = layer(t)
            if lm is not None and lt is not None and lt > lm:
                problems.append(f"{show(m)} ({LAYERS[lm] if lm < len(LAYERS) else 'node'}) "
                                f"imports {show(t)} ({LAYERS[lt] if lt < len(LAYERS) else 'node'})")
            if lm is None and m[0] in CEILINGS and lt is not None:
                ceiling = LAYERS.index(CEILINGS[m[0]])
                if lt > ceiling:
                    problems.append(f"{show(m)} may import src/ros up to {CEILINGS[m[0]]} only, "
                                    f"imports {show(t)}")
            if m == ("ros", "inbound") or (len(m) > 1 and m[:2] == ("ros", "inbound")):
                if len(t) > 1 and t[:2] == ("ros", "outbound"):
                    problems.append(f"{show(m)} (inbound) imports the outbound side: {show(t)}")

    n_edges = sum(len(t) for t in edges.values())
    for p in sorted(set(problems)):
        print(p)
    print(f"check-layers: {len(modules)} modules, {n_edges} edges, {len(set(problems))} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
