"""The import graph of sim/, learn/, export/ and kiloforge/: no cycles, no torch below learn, every module on its floor
(docs/design.md, "Dependencies run one way")."""
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


#: kiloforge's foundation, the floor below sim: what every package uses and nothing of ours but itself
FOUNDATION = {"kiloforge", "kiloforge.errors", "kiloforge.validate", "kiloforge.io", "kiloforge.progress",
              "kiloforge.cliparse", "kiloforge.interrupts", "kiloforge.sighold", "kiloforge.extras", "kiloforge.plotting",
              "kiloforge.numfmt", "kiloforge.stdio", "kiloforge.xorshift"}
#: the programs, the top floor: the ``__main__`` modules, the ``kiloforge`` command, the console scripts and the
#: command lines that sit above the package they are named after (``python -m sim`` plays policy artifacts)
PROGRAMS = {"sim.__main__", "learn.__main__", "export.__main__", "kiloforge.__main__", "kiloforge.cli",
            "kiloforge.scripts", "kiloforge.sim_cli"}
FLOORS = ("foundation", "sim", "artifact", "export", "learn", "program")


def floor(name: str) -> str:
    """The floor of a module: kiloforge's foundation, the simulator library, kiloforge's artifact and actor floor
    (artifact, policies, actors/), export, learn, or the programs."""
    if name in PROGRAMS:
        return "program"
    if name in FOUNDATION:
        return "foundation"
    top = name.split(".")[0]
    return "artifact" if top == "kiloforge" else top


def back_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a module from a floor above its own, and every import of sim/ into kiloforge beyond the
    foundation and the programs (``sim/__main__.py`` only starts its command line, :mod:`kiloforge.sim_cli`)."""
    out = [f"{name} ({floor(name)}) imports {dep} ({floor(dep)})" for name, deps in sorted(graph.items())
           for dep in sorted(deps) if FLOORS.index(floor(dep)) > FLOORS.index(floor(name))]
    for name, deps in sorted(graph.items()):
        if name.split(".")[0] == "sim":
            allowed = FOUNDATION | (PROGRAMS if name == "sim.__main__" else set())
            out += [f"{name} imports {dep}" for dep in sorted(deps)
                    if dep.split(".")[0] == "kiloforge" and dep not in allowed]
    return out


def test_floors():
    """Every import goes to the module's own floor or one below: foundation < sim < artifact/actor < export < learn
    < programs; no module of sim/ imports kiloforge's artifact/actor floor."""
    graph = _graph()
    assert floor("kiloforge.policies") == floor("kiloforge.actors.gru") == "artifact"
    assert not FOUNDATION - set(graph) and not PROGRAMS - set(graph), "a listed module does not exist"
    assert back_arrows(graph) == []
    assert "kiloforge.sim_cli" in graph["sim.__main__"] and "kiloforge.policies" in graph["kiloforge.sim_cli"]


def test_floor_check_sees_back_arrows():
    """The floor check flags sim (its __main__ too) importing the artifact floor and learn importing a program, and
    lets the artifact floor import sim and the foundation."""
    assert back_arrows({"sim.__main__": {"kiloforge.policies"}, "learn.onnx_export": {"kiloforge.cli"},
                        "kiloforge.artifact": {"sim.config", "kiloforge.io"}, "sim.env": {"kiloforge.progress"}}) == [
        "learn.onnx_export (learn) imports kiloforge.cli (program)", "sim.__main__ imports kiloforge.policies"]
