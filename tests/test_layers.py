"""The layers of the house, read from the code's imports.

Every ``import`` of a tiledsm module counts, at module level or inside a
function (a function-level import is a dependency all the same; it only
defers it). The rules (README, "Architecture"):

- no circle between modules;
- ``tiledsm.geometry`` is pure: it imports neither ``tiledsm.io`` nor any
  other tiledsm layer above it, nor dask or rasterio;
- dependencies point one way: cli -> pipelines/workflows -> plan -> stages
  -> io -> geometry -> errors;
- no private name (``_x``) imported from another module;
- no module over 600 lines;
- dask's public API only: no graph built by hand (``HighLevelGraph``,
  ``dask.highlevelgraph``, ``dask.core``, ``dask._task_spec``; issue 35).
"""

from __future__ import annotations

import ast
from pathlib import Path

import tiledsm

ROOT = Path(tiledsm.__file__).resolve().parent


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The tiledsm module ``name`` lives in (a name imported from a
    package's ``__init__`` is attributed to the package)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imports(path: Path, modules: dict[str, Path]) -> list[tuple[str, str | None, int]]:
    """``(module, imported name or None, line)`` of every tiledsm import in
    ``path``, and ``("<ext>:pkg", None, line)`` for dask/rasterio."""
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                if top == "tiledsm":
                    out.append((_resolve(a.name, modules), None, node.lineno))
                elif top in ("dask", "distributed", "rasterio", "rioxarray"):
                    out.append((f"<ext>:{top}", None, node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                src = f"{base}.{node.module}" if node.module else base
            else:
                src = node.module or ""
            top = src.split(".")[0]
            if top in ("dask", "distributed", "rasterio", "rioxarray"):
                out.append((f"<ext>:{top}", None, node.lineno))
                continue
            if top != "tiledsm":
                continue
            for a in node.names:
                sub = f"{src}.{a.name}"
                target = sub if sub in modules else _resolve(src, modules)
                out.append((target, None if sub in modules else a.name, node.lineno))
    return [(m, n, ln) for m, n, ln in out if m != me]


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: {t for t, _, _ in _imports(p, modules) if not t.startswith("<ext>")} for m, p in modules.items()}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    graph = _graph()
    # a package's __init__ re-exports its modules: an import of the package
    # from one of its own modules is what makes a circle, and is reported too
    circles = _circles(graph)
    text = "\n".join(
        " <-> ".join(c) + "\n    " + "; ".join(f"{a} -> {b}" for a in c for b in sorted(graph[a] & set(c)))
        for c in circles
    )
    assert not circles, f"import circles:\n{text}"


def test_geometry_is_pure():
    modules = _modules()
    bad = []
    for m, p in modules.items():
        if not (m == "tiledsm.geometry" or m.startswith("tiledsm.geometry.")):
            continue
        for target, name, line in _imports(p, modules):
            allowed = target.startswith("tiledsm.geometry") or target == "tiledsm.errors"
            if not allowed:
                bad.append(f"{p.relative_to(ROOT.parent)}:{line} imports {target}")
    assert not bad, "geometry must not read files or build graphs:\n" + "\n".join(bad)


def test_no_private_name_across_modules():
    modules = _modules()
    bad = []
    for m, p in modules.items():
        for target, name, line in _imports(p, modules):
            if name and name.startswith("_") and not name.startswith("__"):
                bad.append(f"{p.relative_to(ROOT.parent)}:{line} imports {name} from {target}")
    assert not bad, "\n".join(bad)


def test_no_module_over_600_lines():
    long = {str(p.relative_to(ROOT.parent)): n for p in ROOT.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 600}
    assert not long, long


def test_the_graph_reader_sees_a_circle(tmp_path):
    # the oracle for the tests above: a made-up circle is found
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


#: dask modules and names a graph built by hand needs; the package uses none
DASK_INTERNALS = ("dask.highlevelgraph", "dask.core", "dask._task_spec")
HAND_BUILT = ("HighLevelGraph", "Task", "TaskRef", "Alias", "DataNode")


def _dask_internals(source: str, filename: str) -> list[tuple[int, str]]:
    """``(line, what)`` of every import of a dask internal module, or of a
    hand-built graph's name, in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names
                      if any(a.name == m or a.name.startswith(m + ".") for m in DASK_INTERNALS)]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dask":
            if any(node.module == m or node.module.startswith(m + ".") for m in DASK_INTERNALS):
                found.append((node.lineno, node.module))
            found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names if a.name in HAND_BUILT]
        elif isinstance(node, ast.Attribute) and node.attr in HAND_BUILT[:1]:
            found.append((node.lineno, node.attr))
        elif isinstance(node, ast.Name) and node.id == HAND_BUILT[0]:
            found.append((node.lineno, node.id))
    return found


def test_no_graph_built_by_hand():
    bad = [f"{p.relative_to(ROOT.parent)}:{line} uses {what}"
           for p in sorted(ROOT.rglob("*.py")) for line, what in _dask_internals(p.read_text(), str(p))]
    assert not bad, "dask's public API only:\n" + "\n".join(bad)


def test_the_dask_reader_sees_a_hand_built_graph():
    # the oracle for the test above: the former engine's imports are found
    assert _dask_internals("from dask.highlevelgraph import HighLevelGraph\n", "x") == [
        (1, "dask.highlevelgraph"), (1, "dask.highlevelgraph.HighLevelGraph")]
    assert _dask_internals("import dask\ng = dask.highlevelgraph.HighLevelGraph(layers, deps)\n", "x") == [
        (2, "HighLevelGraph")]
    assert _dask_internals("import dask._task_spec as ts\nfrom dask.core import flatten\n", "x") == [
        (1, "dask._task_spec"), (2, "dask.core")]
    assert _dask_internals("import dask.array as da\nfrom dask import delayed\n", "x") == []
