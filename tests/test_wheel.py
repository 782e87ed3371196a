"""The installed package works where its users work: a wheel in a fresh venv, run outside the repository.

Builds a wheel from a copy of the source tree, installs it into a new virtual environment (no system
site-packages, so no editable kiloforge can leak in; the core dependencies come from the package
index, pip's cache makes reruns quick) and runs the README's Quick start and the --verify ladder
from an empty directory. About a minute; CI runs it (it proves the Quick start). Without a reachable
package index it skips locally and fails in CI.
"""
from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import venv
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.avr_tools import require_avr
from export.verify import avr
from kiloforge import __version__

pytestmark = pytest.mark.wheel

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("kiloforge", "sim", "learn", "export", "firmware_templates")
JUNK = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__", "*.pyc", ".pytest_cache",
                              ".hypothesis", "runs", ".venv", "venv", ".whl", ".gl", "out")


@dataclass(frozen=True)
class Installed:
    wheel: Path
    python: Path  #: the fresh venv's interpreter
    bin: Path
    env: dict  #: environment for commands run with it (no PYTHONPATH, a private build cache)
    tmp: Path


def _run(cmd, *, cwd: Path | None = None, env: dict | None = None, timeout: float = 600):
    return subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def _index_unreachable_or_fail(what: str, res: subprocess.CompletedProcess) -> None:
    """Skip (locally) when the package index cannot be reached, else fail with pip's output."""
    probe = _run([sys.executable, "-m", "pip", "index", "versions", "setuptools"], timeout=120)
    out = (res.stdout + res.stderr).strip()[-3000:]
    if probe.returncode != 0 and not os.environ.get("CI"):
        pytest.skip(f"package index unreachable ({probe.stderr.strip()[-200:]}); cannot {what}")
    pytest.fail(f"{what} failed (rc {res.returncode}):\n{out}")


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=JUNK)  # built in a copy: no build/ left in (or stale files taken from) the tree
    dist = tmp / "dist"
    res = _run([sys.executable, "-m", "pip", "wheel", src, "--no-deps", "-q", "-w", dist])
    if res.returncode != 0:
        _index_unreachable_or_fail("build the wheel", res)
    (wheel,) = dist.glob("kiloforge-*.whl")
    env_dir = tmp / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False, clear=True).create(env_dir)
    bindir = env_dir / ("Scripts" if os.name == "nt" else "bin")
    python = bindir / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(PYTHONNOUSERSITE="1", KILOFORGE_CACHE=str(tmp / "cache"), PATH=f"{bindir}{os.pathsep}{env['PATH']}")
    res = _run([python, "-m", "pip", "install", "-q", wheel], env=env)
    if res.returncode != 0:
        _index_unreachable_or_fail("install the wheel and its dependencies", res)
    return Installed(wheel=wheel, python=python, bin=bindir, env=env, tmp=tmp)


def _workdir(inst: Installed, name: str, stray: bool = False) -> Path:
    d = inst.tmp / name
    d.mkdir()
    if stray:
        for mod in ("learn", "sim", "export"):
            (d / f"{mod}.py").write_text("raise SystemExit('a stray module of the user was imported')\n")
    return d


def _export(inst: Installed, cwd: Path, *args: str, exe: str | None = None) -> subprocess.CompletedProcess:
    cmd = [inst.bin / exe] if exe else [inst.python, "-m", "export"]
    res = _run([*cmd, *args], cwd=cwd, env=inst.env)
    assert res.returncode == 0, f"{' '.join(map(str, cmd + list(args)))} in {cwd} exited {res.returncode}:\n" \
                                f"{(res.stdout + res.stderr)[-3000:]}"
    return res


def _wrote(cwd: Path, out: str) -> None:
    text = (cwd / out).read_text()
    assert "DO NOT EDIT" in text and "int main(void)" in text
    assert "int main(void)" in (cwd / "kilobot_target.c").read_text()
    assert f'"generator_version": "{__version__}"' in (cwd / f"{out}.manifest.json").read_text()


def test_wheel_holds_every_runtime_file(installed):
    """Every non-Python file of the packages (templates, C, headers, data, py.typed) and the LICENSE is in the wheel."""
    names = set(zipfile.ZipFile(installed.wheel).namelist())
    want = {p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*")
            if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts}
    assert {"export/verify/simavr_run.c", "export/data/default_policy.npz", "kiloforge/py.typed"} <= want
    assert want - names == set(), f"missing from the wheel: {sorted(want - names)}"
    meta = zipfile.ZipFile(installed.wheel).read(f"kiloforge-{__version__}.dist-info/METADATA").decode()
    assert f"Version: {__version__}" in meta and "License-Expression: MIT" in meta and "Project-URL: Homepage" in meta
    assert f"kiloforge-{__version__}.dist-info/licenses/LICENSE" in names


def test_quick_start_outside_the_repository(installed):
    """`python -m export --out kp.c` in an empty directory uses the installed package and writes the files."""
    cwd = _workdir(installed, "quick")
    where = _run([installed.python, "-c", "import export, kiloforge; print(export.__file__, kiloforge.__version__)"],
                 cwd=cwd, env=installed.env)
    assert where.returncode == 0 and str(installed.tmp / "venv") in where.stdout, where.stdout + where.stderr
    assert where.stdout.split()[1] == __version__
    _export(installed, cwd, "--out", "kp.c")
    _wrote(cwd, "kp.c")


def test_verify_host_outside_the_repository(installed):
    """`--verify host` from the installed package builds the firmware with its own harness files, bit-exact."""
    cwd = _workdir(installed, "host")
    res = _export(installed, cwd, "--out", "kp2.c", "--verify", "host")
    assert "host build vs emulator: bit-exact" in res.stdout
    _wrote(cwd, "kp2.c")


def test_verify_avr_outside_the_repository(installed):
    """`--verify avr` from the installed package builds the simavr runner from its package data and matches."""
    require_avr(simulate=True)
    cwd = _workdir(installed, "avr")
    res = _export(installed, cwd, "--out", "kp3.c", "--verify", "avr")
    assert "simavr (ATmega328P, 8 MHz) vs emulator: bit-exact" in res.stdout
    assert list((installed.tmp / "cache").glob("kf_simavr-*")), "the runner was not built from the wheel's source"
    _wrote(cwd, "kp3.c")


def test_console_script_ignores_stray_modules(installed):
    """`kiloforge-export` in a directory holding stray learn.py, sim.py and export.py still uses the package."""
    cwd = _workdir(installed, "stray", stray=True)
    _export(installed, cwd, "--out", "kp.c", exe="kiloforge-export")
    _wrote(cwd, "kp.c")


def test_hostile_inputs_outside_the_repository(installed):
    """tests/hostile_cases.py run by the installed package in an empty directory: every case one line / exit 2, or (a
    planted build runner) exit 0 without running it."""
    cwd = _workdir(installed, "hostile")
    script = cwd / "hostile_cases.py"
    shutil.copy(ROOT / "tests" / "hostile_cases.py", script)
    res = _run([installed.python, script], cwd=cwd, env=installed.env)
    rows = [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{")]
    bad = [r for r in rows if not r["ok"]]
    assert res.returncode == 0 and len(rows) >= 8 and not bad, (bad or res.stdout + res.stderr)[-3000:]
    if os.environ.get("CI") or avr.missing_tools(simulate=True) is None:
        assert any(r["case"].startswith("planted runner") for r in rows), "the planted-runner case did not run"


@contextmanager
def _learn_extra(installed: Installed):
    """Let the fresh core-only venv import this interpreter's torch, tyro and numba (a .pth appended after the
    venv's own site-packages, so the wheel's kiloforge and the venv's packages come first); removed after."""
    torch = pytest.importorskip("torch", reason="training needs the learn extra (torch)")
    site = next((installed.tmp / "venv").glob("lib/python*/site-packages"))
    pth = site / "zz_learn_extra.pth"
    pth.write_text(str(Path(torch.__file__).resolve().parents[1]) + "\n")
    try:
        yield
    finally:
        pth.unlink()


#: flags appended to the README's commands so the round trip takes about a minute (a repeated flag: the last wins)
SHORT = {"train-es": ["--generations", "1", "--pairs", "2", "--eval-episodes", "1", "--eval-steps", "30",
                      "--episode-steps", "30", "--demo-robot-episodes", "8", "--bc-updates", "20"],
         "evaluate": ["--robots", "4", "--episodes", "2", "--steps", "30"],
         "verify": ["--robots", "4", "--episodes", "2", "--steps", "30"]}


def _readme_round_trip() -> list[list[str]]:
    """The commands of the README's "From a training run to robots" block, continuation lines joined."""
    text = (ROOT / "README.md").read_text().split("## From a training run to robots", 1)[1].split("\n## ", 1)[0]
    block = re.sub(r"\\\n\s*", " ", text)
    return [shlex.split(line.strip()) for line in block.splitlines() if line.strip().startswith("python -m ")]


def test_readme_round_trip_outside_the_repository(installed):
    """The README's round trip (train-es, its fine-tune, evaluate, export --verify host, export verify), shortened
    by flags, from the installed wheel in an empty directory: each command succeeds and hands the next its file."""
    cmds = _readme_round_trip()
    assert [c[2] for c in cmds] == ["learn", "learn", "learn", "export", "export"], cmds
    cwd = _workdir(installed, "roundtrip")
    out = {}
    with _learn_extra(installed):
        for cmd in cmds:
            sub = cmd[3] if cmd[2] == "learn" or cmd[3:4] == ["verify"] else "export"
            res = _run([installed.python, *cmd[1:], *SHORT.get(sub, []), "--quiet"], cwd=cwd, env=installed.env)
            assert res.returncode in (0, 1) if sub == "verify" else res.returncode == 0, \
                (cmd, (res.stdout + res.stderr)[-3000:])
            out[sub] = res.stdout
    policy = next(a for c in cmds if c[2:4] == ["learn", "evaluate"] for a in c if a.endswith(".npz"))
    assert (cwd / policy).is_file() and (cwd / "kilobot_policy.c").is_file()
    assert "host build vs emulator: bit-exact" in out["export"] and "closed loop:" in out["verify"]


def test_example_task_round_trip_outside_the_repository(installed):
    """examples/dispersion.py, a user's task in one file, through the installed package outside the repository:
    train-es from random weights, evaluate, export --verify host and export verify, each naming the task."""
    cwd = _workdir(installed, "task")
    shutil.copy(ROOT / "examples" / "dispersion.py", cwd / "dispersion.py")
    task = ["--task", "dispersion.py:Dispersion"]
    steps = [
        ["learn", "train-es", *task, "--demo-policy", "none", "--robots", "4", "--generations", "2", "--pairs", "4",
         "--eval-episodes", "2", "--eval-every", "1", "--quiet", "--out", "run"],
        ["learn", "evaluate", *task, "--policy", "run/policy_best.npz", "--robots", "4", "--episodes", "4",
         "--steps", "60", "--quiet", "--out", "eval"],
        ["export", *task, "--policy", "run/policy_best.npz", "--out", "disp.c", "--verify", "host", "--no-avr",
         "--quiet"],
        ["export", "verify", *task, "--policy", "run/policy_best.npz", "--robots", "4", "--episodes", "2", "--quiet"],
    ]
    out = []
    with _learn_extra(installed):
        for cmd in steps:
            res = _run([installed.bin / "kiloforge", *cmd], cwd=cwd, env=installed.env)
            assert res.returncode in (0, 1), (cmd, res.stdout[-2000:], res.stderr[-2000:])  # verify: 1 = FAIL
            out.append(res.stdout)
    meta = json.loads(bytes(__import__("numpy").load(cwd / "run" / "policy_best.npz")["meta"]).decode())
    assert meta["task"] == {"name": "dispersion", "version": 2}
    ev = json.loads((cwd / "eval" / "evaluation.json").read_text())
    assert ev["task"]["primary_metric"] == "final_alone" and {"hand-written", "random"} <= set(ev["robots"]["4"]["metrics"])
    assert "bit-exact" in out[2] and (cwd / "disp.c").is_file() and not (cwd / "kilobot_target.c").exists()
    assert "final fraction of robots alone int8/float" in out[3]
