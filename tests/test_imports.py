"""The import graph of sim/, learn/, export/ and kiloforge/: no cycles, no torch below learn, sim below export."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sim", "learn", "export", "kiloforge")


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every .py of the packages."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Every project module ``name`` imports anywhere in its file (function-local and TYPE_CHECKING
    imports included), with the packages that importing it initialises."""
    is_pkg = path.name == "__init__.py"
    here = name.split(".") if is_pkg else name.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(here[:len(here) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)
    ancestors = {".".join(name.split(".")[:k]) for k in range(1, name.count(".") + 1)}
    deps = set()
    for mod in found:
        parts = mod.split(".")
        for k in range(1, len(parts) + 1):  # importing a.b.c runs a, a.b and a.b.c
            dep = ".".join(parts[:k])
            if dep in known and dep not in ancestors and dep != name:
                deps.add(dep)
    return deps


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {name: _imports(name, path, set(mods)) for name, path in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
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
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    """No module of sim, learn, export or kiloforge reaches itself through imports (local ones included)."""
    graph = _graph()
    assert len(graph) > 60 and graph["export.cli.main"], "the graph was not built"
    assert _cycles(graph) == []


def test_cycle_finder_finds_a_cycle():
    """The cycle finder reports a two-module cycle and ignores a chain."""
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_layers():
    """sim and kiloforge never import export or learn; export never imports learn; nothing outside learn imports torch."""
    mods = _modules()
    graph = _graph()
    for name, deps in graph.items():
        top = name.split(".")[0]
        bad = {d for d in deps if d.split(".")[0] in {"sim": ("export", "learn"), "kiloforge": ("export", "learn"),
                                                       "export": ("learn",), "learn": ()}[top]}
        assert not bad, f"{name} imports {sorted(bad)}"
        if top != "learn":
            tree = ast.parse(mods[name].read_text(encoding="utf-8"))
            names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
            names |= {(n.module or "").split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
            assert "torch" not in names, f"{name} imports torch"
