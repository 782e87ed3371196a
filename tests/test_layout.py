"""Where the scripts live: benchmarks in tests/bench, soak runs in tests/soak, experiments and data generators in
experiments/ and tools/, each indexed, all importable as modules of the repository root without editing sys.path."""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT_DIRS = ("tests", "experiments", "tools")


def path_edits(source: str) -> list[int]:
    """Lines of ``source`` that change ``sys.path``: an assignment to it or to a slice of it, or a call of one of
    its methods (insert, append, extend, ...)."""
    def is_sys_path(node: ast.AST) -> bool:
        return (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
                and node.value.id == "sys")

    lines = []
    for node in ast.walk(ast.parse(source)):
        targets = (node.targets if isinstance(node, ast.Assign) else [node.target]
                   if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])
        for t in targets:
            if is_sys_path(t) or (isinstance(t, ast.Subscript) and is_sys_path(t.value)):
                lines.append(node.lineno)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and is_sys_path(node.func.value):
            lines.append(node.lineno)
    return sorted(lines)


def test_path_edit_finder():
    """The finder sees an insert, a slice assignment and an append, and not a read of sys.path."""
    insert = "sys.path." + "insert"  # spelt apart, so that grepping the tree for the call finds nothing here
    src = f"import sys\n{insert}(0, 'x')\nsys.path[:0] = ['y']\nsys.path.append('z')\nprint(sys.path[0])\n"
    assert path_edits(src) == [2, 3, 4]


def test_no_script_edits_sys_path():
    """No Python file of tests/, experiments/ or tools/ changes sys.path: they run against the installed package."""
    found = [f"{f.relative_to(ROOT)}:{line}" for d in SCRIPT_DIRS for f in sorted((ROOT / d).rglob("*.py"))
             for line in path_edits(f.read_text(encoding="utf-8"))]
    assert found == []


def _indexed(folder: str) -> set[str]:
    return set(re.findall(r"^\| `(\w+\.py)` \|", (ROOT / folder / "README.md").read_text(encoding="utf-8"), re.M))


def test_every_experiment_and_tool_is_indexed():
    """experiments/README.md and tools/README.md have a row for each of their scripts, and no row for a missing one."""
    for folder in ("experiments", "tools"):
        scripts = {f.name for f in (ROOT / folder).glob("*.py") if f.name != "__init__.py"}
        assert scripts and _indexed(folder) == scripts, folder


def test_scripts_import_as_modules():
    """Every benchmark, soak run, experiment and tool imports as a module from the repository root (how
    ``python -m tests.bench.NAME`` runs it), and an experiment answers --help that way."""
    modules = [".".join(f.relative_to(ROOT).with_suffix("").parts) for d in ("tests/bench", "tests/soak", "experiments",
                                                                           "tools")
               for f in sorted((ROOT / d).glob("*.py")) if f.name != "__init__.py"]
    assert len(modules) > 15
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\nprint('ok')"
    r = subprocess.run([sys.executable, "-c", code, *modules], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
    r = subprocess.run([sys.executable, "-m", "experiments.oracle_push", "--help"], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and "--robots" in r.stdout, r.stderr[-2000:]
