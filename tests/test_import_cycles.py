"""No import cycles among the modules of isobench's packages.

The import graph is read from the source with :mod:`ast` (nothing is imported), counting every
import statement wherever it stands, inside functions too: a function-level import that closes a
cycle is still a cycle (it only moves the failure from import time to call time, and it hides
which module builds on which).  Relative imports are resolved against the importing module's
package; ``from package import name`` counts as an import of the submodule ``package.name``
when that submodule exists, else of ``package`` itself.

An import of a package (``import reference``, or ``from reference import Sphere``) is an edge to
its ``__init__``; ``__init__`` re-exports, so ``reference.cases`` importing ``reference`` and
``reference/__init__.py`` importing ``reference.cases`` is a cycle, as it would be at import
time.  Edges from a module to its own package's ``__init__`` that Python creates implicitly
(importing ``a.b`` runs ``a/__init__``) are not counted: they are not written in the source.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Packages whose modules must form an acyclic import graph (imports inside functions count).
PACKAGES = ("reference", "bench", "impls")


def module_files(root: Path, packages) -> dict[str, Path]:
    """Dotted module name → file, for every ``.py`` file under each package directory."""
    out = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _package_of(module: str, path: Path) -> str:
    """The package a module's relative imports are resolved against."""
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def import_edges(module: str, path: Path, known: set[str]) -> set[str]:
    """Modules of ``known`` that ``module`` (at ``path``) imports anywhere in its source."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _package_of(module, path)
    found = set()

    def closest_known(name: str) -> str | None:
        # ``import a.b.c`` imports a.b.c (and runs a, a.b on the way); a name that is not a
        # module of ours (a class, a third-party package) resolves to its nearest known prefix.
        while name:
            if name in known:
                return name
            name = name.rpartition(".")[0]
        return None

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                hit = closest_known(alias.name)
                if hit:
                    found.add(hit)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                if node.level > 1:
                    base = base[: len(base) - (node.level - 1)]
                base_name = ".".join(base + ([node.module] if node.module else []))
            else:
                base_name = node.module or ""
            for alias in node.names:
                sub = f"{base_name}.{alias.name}" if base_name else alias.name
                hit = sub if sub in known else closest_known(base_name)
                if hit:
                    found.add(hit)
    found.discard(module)
    return found


def import_graph(root: Path, packages) -> dict[str, set[str]]:
    files = module_files(root, packages)
    known = set(files)
    return {m: import_edges(m, p, known) for m, p in files.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted:
    every import cycle lies inside one of them."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v):
        # Recursive Tarjan; the graph has a few hundred nodes, far below the recursion limit.
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def describe(graph: dict[str, set[str]], component: list[str]) -> str:
    """The component and the edges inside it, for the failure message."""
    comp = set(component)
    edges = [f"  {a} -> {b}" for a in component for b in sorted(graph[a] & comp)]
    return "cycle among " + ", ".join(component) + ":\n" + "\n".join(edges)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle(package):
    # Graph over every package so that a cycle through another package (reference → bench →
    # reference) is caught too; the test of a package reports the cycles that touch it.
    graph = import_graph(ROOT, PACKAGES)
    cycles = [c for c in find_cycles(graph) if any(m == package or m.startswith(package + ".") for m in c)]
    assert not cycles, "\n".join(describe(graph, c) for c in cycles)


#: The layers, top to bottom: a module imports only from its own layer's package or from a lower
#: layer.  ``python -m bench`` starts the command line, which drives everything; the report
#: reads what runs and studies wrote; the studies, the claims and the runs measure methods of
#: impls; impls implements them; reference answers exactly.  Nothing below knows what is above
#: (bench.run never imports a command, a study or the report; impls never imports bench).
LAYERS = (("bench.__main__",), ("bench.commands",), ("bench.report",), ("bench.studies", "bench.claims"), ("bench.run",),
          ("impls",), ("reference",))


def layer_of(module: str) -> tuple[int, str] | None:
    """(rank of the module's layer, its package in the layer), or None outside every layer."""
    for rank, packages in enumerate(LAYERS):
        for pkg in packages:
            if module == pkg or module.startswith(pkg + "."):
                return rank, pkg
    return None


def layering_violations(graph: dict[str, set[str]]) -> list[str]:
    """Edges that go up a layer or sideways between two packages of one layer."""
    out = []
    for a in sorted(graph):
        la = layer_of(a)
        for b in sorted(graph[a]):
            lb = layer_of(b)
            if la is None or lb is None or la[1] == lb[1]:
                continue
            if lb[0] <= la[0]:
                out.append(f"{a} -> {b} ({la[1]} may import only from layers below it: "
                           f"{', '.join(p for ps in LAYERS[la[0] + 1:] for p in ps)})")
    return out


def test_layering():
    graph = import_graph(ROOT, PACKAGES)
    bad = layering_violations(graph)
    assert not bad, "\n".join(bad)


def test_layering_checker_finds_an_upward_import():
    graph = {"bench.run.runner": {"bench.report.build", "impls.registry"}, "bench.report.build": {"bench.run.runner"},
             "bench.studies.speed": {"bench.claims.stats"}, "impls.registry": set()}
    assert [v.split(" (")[0] for v in layering_violations(graph)] == [
        "bench.run.runner -> bench.report.build", "bench.studies.speed -> bench.claims.stats"]


def test_checker_finds_a_cycle(tmp_path):
    # The checker itself: a planted cycle through a function-level relative import is found,
    # and the acyclic remainder is not reported.
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..a import x\n    return x\n")
    (pkg / "c.py").write_text("from pkg.sub.b import f\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert find_cycles(graph) == [["pkg.a", "pkg.sub.b"]]


if __name__ == "__main__":  # a report over every package
    g = import_graph(ROOT, PACKAGES)
    cycles = find_cycles(g)
    print("\n".join(describe(g, c) for c in cycles) if cycles else "no import cycles")
