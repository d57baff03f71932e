"""The package's imports: no cycles and no import against the layers (``LAYERS`` below).

Read from the source with ``ast`` (no module is imported), counting imports inside functions too, since a
late import is still a dependency; importing ``a.b.c`` also runs ``a`` and ``a.b``, so a module depends on
its target's parent packages as well. ``kernels/`` is imported as ``ti_fusion.kernels``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Lowest first. A module may import its own group and any group of a lower rank; groups of one rank are
# peers and may not import each other. A module belongs to the group of its longest matching prefix.
LAYERS: list[tuple[int, str, tuple[str, ...]]] = [
    (0, "leaves", ("ti_fusion", "ti_fusion.errors", "ti_fusion.geometry", "ti_fusion.sensor", "ti_fusion.camera",
                   "ti_fusion.frame", "ti_fusion.timing", "ti_fusion.interrupts", "ti_fusion.frontend", "ti_fusion.launches",
                   "ti_fusion.io", "ti_fusion.io.formats", "ti_fusion.io.tables", "ti_fusion.status",
                   "ti_fusion.tracking", "ti_fusion.mapping", "ti_fusion.loop", "ti_fusion.slam",
                   "ti_fusion.synthetic", "ti_fusion.evaluation", "ti_fusion.reference")),
    (1, "config", ("ti_fusion.config",)),
    (2, "files", ("ti_fusion.io.outputs", "ti_fusion.io.ply", "ti_fusion.io.trajectory", "ti_fusion.io.mesh_files",
                  "ti_fusion.io.mcap_log", "ti_fusion.io.prefetch", "ti_fusion.io.frame_workers",
                  "ti_fusion.io.live", "ti_fusion.io.map_files")),
    (3, "kernels", ("ti_fusion.backend", "ti_fusion.kernels")),
    (4, "synthetic", ("ti_fusion.synthetic.",)),
    (5, "tracking", ("ti_fusion.tracking.",)),
    (5, "mapping", ("ti_fusion.mapping.",)),
    (5, "datasets", ("ti_fusion.io.datasets", "ti_fusion.io.registration")),
    (5, "evaluation", ("ti_fusion.evaluation.",)),
    (6, "loop", ("ti_fusion.loop.",)),
    (6, "reference", ("ti_fusion.reference.",)),
    (6, "sinks", ("ti_fusion.sinks",)),
    (7, "slam", ("ti_fusion.slam.",)),
    (8, "cli", ("ti_fusion.cli", "ti_fusion.__main__", "ti_fusion.batch")),
]

# Imports against the layers that are known and being removed; the test fails on any other, and on an entry
# here that no longer happens, so the lists can only shrink.
KNOWN: set[tuple[str, str]] = set()
KNOWN_CYCLES: list[list[str]] = []


def modules() -> dict[str, Path]:
    mods = {}
    for base, pkg in ((ROOT / "ti_fusion", "ti_fusion"), (ROOT / "kernels", "ti_fusion.kernels")):
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("").parts
            rel = rel[:-1] if rel[-1] == "__init__" else rel
            mods[".".join((pkg, *rel))] = path
    return mods


def _target_names(node: ast.AST, module: str, is_package: bool) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    base = node.module or ""
    if node.level:  # relative: resolve against this module's package
        parts = module.split(".")
        parts = parts if is_package else parts[:-1]
        parts = parts[: len(parts) - (node.level - 1)]
        base = ".".join(parts + ([base] if base else []))
    return [base] + [f"{base}.{a.name}" for a in node.names]


def import_graph() -> dict[str, set[str]]:
    """module → the modules it imports (package modules included), anywhere in its source."""
    mods = modules()
    graph = {m: set() for m in mods}
    for m, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for name in _target_names(node, m, path.name == "__init__.py"):
                if name == "kernels" or name.startswith("kernels."):
                    name = "ti_fusion." + name
                if name not in mods:
                    continue
                parts = name.split(".")
                for k in range(1, len(parts) + 1):  # the target and the packages its import runs
                    target = ".".join(parts[:k])
                    if target in mods and target != m and not m.startswith(target + "."):
                        graph[m].add(target)
    return graph


def layer_of(module: str) -> tuple[int, str]:
    best = None
    for rank, group, prefixes in LAYERS:
        for p in prefixes:
            hit = module == p.rstrip(".") or (p.endswith(".") and module.startswith(p)) \
                  or (not p.endswith(".") and module.startswith(p + "."))
            if hit and (best is None or len(p) > best[0]):
                best = (len(p), rank, group)
    assert best is not None, f"{module} is in no layer: add it to LAYERS in tests/test_imports.py"
    return best[1], best[2]


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]; counter[0] += 1; stack.append(root); on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]; counter[0] += 1; stack.append(w); on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    scc = []
                    while True:
                        w = stack.pop(); on.discard(w); scc.append(w)
                        if w == v:
                            break
                    if len(scc) > 1:
                        out.append(sorted(scc))
    return out


def against_layers(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    bad = set()
    for m, targets in graph.items():
        rank, group = layer_of(m)
        for t in targets:
            t_rank, t_group = layer_of(t)
            if t_group != group and t_rank >= rank:
                bad.add((m, t))
    return bad


def test_every_module_has_a_layer():
    for m in modules():
        layer_of(m)


def test_no_import_cycles():
    found = [c for c in cycles(import_graph()) if c not in KNOWN_CYCLES]
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_no_import_against_the_layers():
    bad = against_layers(import_graph())
    new = sorted(bad - KNOWN)
    assert not new, "imports against the layers (see LAYERS in tests/test_imports.py):\n" + "\n".join(
        f"{m} ({layer_of(m)[1]}) imports {t} ({layer_of(t)[1]})" for m, t in new)
    gone = sorted(KNOWN - bad)
    assert not gone, f"remove from KNOWN, these no longer happen: {gone}"


def test_the_check_sees_a_late_import_and_a_cycle():
    """The checker itself: a function-level import counts, and a two-module loop is a cycle."""
    tree = ast.parse("def f():\n    from ti_fusion.config import Config\n")
    names = [n for node in ast.walk(tree) for n in _target_names(node, "ti_fusion.geometry", False)]
    assert "ti_fusion.config" in names
    assert cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert against_layers({"ti_fusion.geometry": {"ti_fusion.config"}, "ti_fusion.config": set()}) \
        == {("ti_fusion.geometry", "ti_fusion.config")}
