"""Kill a command at a random moment and check what it left (tests/test_kill.py runs a few, tests/bench/kill_test.py
hundreds). An export must leave the old complete set or the new complete set; a present manifest always
describes the files beside it; after the next run's recovery no temporary is left; the message of an
interrupted run says what was written. A killed training run must resume (or restart) and finish."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
EXPORT_FILES = ("kilobot_policy.c", "kilobot_target.c", "kilobot_policy.c.manifest.json")
EXPORT_ARGS = ["--robots-calib", "2", "--calib-steps", "4", "--no-avr", "--no-progress"]
#: what CPython prints when a SIGINT lands in its own start-up, before the program's first line
CPYTHON_START_UP = ("Could not import runpy module", "'import warnings' failed", "'import site' failed")


def export_cmd(out_dir: Path, seed: int) -> list[str]:
    return [sys.executable, "-m", "export", "--out", str(out_dir / EXPORT_FILES[0]), "--seed", str(seed)] + EXPORT_ARGS


def read_set(d: Path) -> dict[str, bytes | None]:
    return {n: (d / n).read_bytes() if (d / n).is_file() else None for n in EXPORT_FILES}


def reference_sets(root: Path) -> tuple[dict, dict, float]:
    """The old set (seed 1, exported in this process) and the new set (seed 2, as a program, uninterrupted),
    and how long the program takes."""
    import contextlib
    import io

    from export.cli.main import main

    d1, d2 = root / "ref1", root / "ref2"
    d1.mkdir(parents=True, exist_ok=True)
    d2.mkdir(parents=True, exist_ok=True)
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(export_cmd(d1, 1)[3:]) == 0
    t0 = time.perf_counter()
    subprocess.run(export_cmd(d2, 2), env=ENV, check=True, capture_output=True, timeout=300)
    duration = time.perf_counter() - t0
    old, new = read_set(d1), read_set(d2)
    assert old[EXPORT_FILES[0]] != new[EXPORT_FILES[0]], "seeds 1 and 2 give the same firmware"
    return old, new, duration


def hidden(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


@dataclass
class KillResult:
    signal: str
    moment: str  #: "uniform" (anywhere in the run), "publish" (once the set is staged), "commit" (once committed)
    rc: int
    before: str  #: the set as a reader finds it right after the kill: old / new / incomplete / mixed
    after: str  #: after the next run's recovery: old / new / ... (must be old or new)
    leftovers: list
    message: str
    problems: list

    @property
    def ok(self) -> bool:
        return not self.problems


def _which(d: Path, old: dict, new: dict) -> str:
    got = read_set(d)
    if got == old:
        return "old"
    if got == new:
        return "new"
    if got[EXPORT_FILES[2]] is None:
        return "incomplete"  # no manifest: a reader knows the set is being replaced
    return "mixed"


def _reached(d: Path, moment: str) -> bool:
    stages = [d / n for n in hidden(d) if n.endswith(".stage")]
    return bool(stages) if moment == "publish" else any((st / "journal.json").exists() for st in stages)


def kill_export(d: Path, old: dict, new: dict, sig: int, moment: str, rng: np.random.Generator,
                duration: float) -> KillResult:
    """Export the new set over the old one in ``d``, send ``sig`` at a random moment, check, recover, check."""
    from export.codegen.manifest import verify_manifest
    from kiloforge.io import recover

    d.mkdir(parents=True, exist_ok=True)
    for n, data in old.items():
        (d / n).write_bytes(data)
    proc = subprocess.Popen(export_cmd(d, 2), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    if moment in ("publish", "commit"):  # wait for the staging directory (or its journal), then a moment more
        t_end = time.perf_counter() + 10 * duration + 30
        while proc.poll() is None and time.perf_counter() < t_end and not _reached(d, moment):
            time.sleep(0.0002)
        time.sleep(rng.uniform(0, 0.06 if moment == "publish" else 0.005))
    else:
        time.sleep(rng.uniform(0, 1.1 * duration))
    if proc.poll() is None:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    rc = proc.returncode
    message = err.decode("utf-8", "replace").strip()
    problems = []
    before = _which(d, old, new)
    if (d / EXPORT_FILES[2]).exists() and verify_manifest(d / EXPORT_FILES[2]):
        problems.append(f"a manifest that does not match its files: {verify_manifest(d / EXPORT_FILES[2])}")
    if before == "mixed":
        problems.append("a mixed set with a manifest")
    recover(d)  # what the next export into d does first
    after = _which(d, old, new)
    left = hidden(d)
    if after not in ("old", "new"):
        problems.append(f"after recovery the set is {after}")
    if left:
        problems.append(f"temporaries left after recovery: {left}")
    # the signal came while the interpreter itself starts or finishes, outside any of our code (CPython then
    # dies of SIGINT, or prints "Could not import runpy module" and a traceback of its own start-up)
    interpreter = rc == -signal.SIGINT or any(m in message for m in CPYTHON_START_UP)
    if sig == signal.SIGINT and not interpreter:
        if rc not in (0, 130):
            problems.append(f"exit status {rc} after SIGINT")
        if "Traceback" in message:
            problems.append("a traceback")
        if rc == 130 and "nothing written" in message and after != "old":
            problems.append("said 'nothing written' but the new set was published")
        if rc == 130 and "interrupted after writing" in message and before != "new":
            problems.append("said it wrote the new set but did not")
    last = "interpreter start-up or exit" if interpreter else message.splitlines()[-1] if message else ""
    return KillResult(signal.Signals(sig).name, moment, rc, before, after, left, last, problems)
