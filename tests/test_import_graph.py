"""No import circle between the package's modules.

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` / ``from ... import`` in a
module of ``r1sim_sumo``, at the top of the file or inside a function, is an edge to the package module it names
(``from pkg import name`` names the submodule ``pkg.name`` when that exists, else ``pkg``). A strongly connected
component of more than one module is a circle; the test names its modules and one edge of each pair.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "r1sim_sumo"


def package_modules(root: Path = PACKAGE) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``root`` (``pkg/__init__.py`` is ``pkg``)."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _target(name: str, modules: dict[str, Path]) -> str | None:
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_edges(modules: dict[str, Path]) -> dict[str, dict[str, int]]:
    """``{module: {imported package module: line of the first such import}}``."""
    edges: dict[str, dict[str, int]] = {}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative import
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                names = [f"{src}.{a.name}" if f"{src}.{a.name}" in modules else src for a in node.names]
            for n in names:
                t = _target(n, modules)
                if t is not None and t != mod:
                    edges.setdefault(mod, {}).setdefault(t, node.lineno)
    return edges


def circles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    nodes = sorted(set(edges) | {t for ts in edges.values() for t in ts})
    counter = 0
    for start in nodes:
        if start in index:
            continue
        work = [(start, iter(sorted(edges.get(start, {}))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, {})))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_circle_finder_finds_a_planted_circle(tmp_path):
    """The checker itself: a two-module circle through a function-level relative import is found, a chain is not."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from .. import a\n    from pkg import c\n")
    (pkg / "c.py").write_text("import os\n")
    mods = package_modules(pkg)
    assert set(mods) == {"pkg", "pkg.sub", "pkg.a", "pkg.sub.b", "pkg.c"}
    assert circles(import_edges(mods)) == [["pkg.a", "pkg.sub.b"]]
    (pkg / "sub" / "b.py").write_text("from pkg import c\n")
    assert circles(import_edges(package_modules(pkg))) == []


def test_no_import_circle_in_the_package():
    mods = package_modules()
    assert len(mods) > 50, f"found only {len(mods)} modules under {PACKAGE}"
    edges = import_edges(mods)
    found = circles(edges)
    if found:
        lines = []
        for comp in found:
            members = set(comp)
            how = [f"{a} -> {b} ({mods[a].relative_to(PACKAGE.parent)}:{ln})"
                   for a in comp for b, ln in sorted(edges.get(a, {}).items()) if b in members]
            lines.append(" <-> ".join(comp) + ":\n    " + "\n    ".join(how))
        pytest.fail("import circles between package modules (move the shared code to a module both import):\n"
                    + "\n".join(lines))
