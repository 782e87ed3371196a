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
EXPORT_ARGS = ["--robots-calib", "2", "--calib-steps", "4", "--no-avr", "--quiet"]
#: what CPython prints when a SIGINT lands in its own start-up, before the program's first line
CPYTHON_START_UP = ("Could not import runpy module", "'import warnings' failed", "'import site' failed")


def in_interpreter(rc: int, message: str) -> bool:
    """The SIGINT came while CPython itself started or exited, outside any of the project's code: CPython's own
    start-up messages, or death by SIGINT without a traceback through the repository."""
    return any(m in message for m in CPYTHON_START_UP) or (rc == -signal.SIGINT and str(ROOT) not in message)


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
    interpreter = in_interpreter(rc, message)
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


# --- trainings ---------------------------------------------------------------------------------------
TRAIN_TINY = ["--robots", "2", "--history", "3", "--episode-steps", "20", "--actor-hidden", "8", "--critic-hidden",
              "16", "--n-envs", "2", "--warmup-episodes", "2", "--batch-size", "8", "--replay-size", "400",
              "--updates-per-step", "0.5", "--eval-every", "40", "--eval-episodes", "2", "--checkpoint-every", "4",
              "--threads", "1", "--quiet"]
TRAIN_EPISODES = 16  #: after the warm-up episodes


def train_cmd(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "learn", "train", *TRAIN_TINY, "--episodes", str(TRAIN_EPISODES), "--out",
            str(out), *extra]


def _run_files(d: Path) -> list[str]:
    """Temporaries anywhere in a run directory."""
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.name.startswith(".") or p.name.endswith(".tmp"))


@dataclass
class TrainKillResult:
    signal: str
    moment: str
    rc: int
    state: str  #: what the kill left: "checkpoint", "no checkpoint" (config.json only), "nothing"
    how: str  #: "resumed", "restarted" or "started again"
    rc_after: int
    episodes: int
    problems: list

    @property
    def ok(self) -> bool:
        return not self.problems


def uninterrupted_training(root: Path) -> tuple[float, int]:
    """How long the short training takes and how many episodes it ends with."""
    from learn.checkpoint import load_checkpoint

    t0 = time.perf_counter()
    subprocess.run(train_cmd(root / "uninterrupted"), env=ENV, check=True, capture_output=True, timeout=600)
    return time.perf_counter() - t0, int(load_checkpoint(root / "uninterrupted")["counters"]["episodes"])


def kill_training(d: Path, sig: int, moment: str, rng: np.random.Generator, duration: float,
                  episodes_done: int) -> TrainKillResult:
    """Start a short training in ``d``, send ``sig`` at a random moment (``uniform``: anywhere in the run;
    ``training``: after its first checkpoint), then continue it the documented way (``--resume``, which
    restarts a run without a checkpoint; the plain command if nothing was written yet); it must finish
    with the uninterrupted run's ``episodes_done`` episodes, its policies and no temporaries."""
    import json

    from learn.checkpoint import load_checkpoint

    proc = subprocess.Popen(train_cmd(d), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.perf_counter()
    if moment == "training":
        while proc.poll() is None and not (d / "checkpoint.pt").exists() and time.perf_counter() - t0 < 600:
            time.sleep(0.01)
    time.sleep(rng.uniform(0, max(0.05, 1.05 * duration - (time.perf_counter() - t0))))
    if proc.poll() is None:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=600)
    rc, message = proc.returncode, err.decode("utf-8", "replace").strip()
    problems = []
    interpreter = in_interpreter(rc, message)
    if sig == signal.SIGINT and not interpreter:
        if rc not in (0, 130):
            problems.append(f"exit status {rc} after SIGINT: {message[-300:]}")
        if "Traceback" in message:
            problems.append(f"a traceback: {message[-300:]}")
    state = ("checkpoint" if (d / "checkpoint.pt").exists() else
             "no checkpoint" if (d / "config.json").exists() else "nothing")
    if state == "nothing":
        how, again = "started again", subprocess.run(train_cmd(d), env=ENV, capture_output=True, timeout=600)
    else:
        how = "resumed" if state == "checkpoint" else "restarted"
        again = subprocess.run(train_cmd(d, "--resume"), env=ENV, capture_output=True, timeout=600)
    episodes = -1
    if again.returncode != 0:
        problems.append(f"{how}: exit {again.returncode}: {again.stderr.decode()[-400:]}")
    else:
        episodes = int(load_checkpoint(d)["counters"]["episodes"])
        if episodes != episodes_done:
            problems.append(f"{how}: {episodes} episodes, not {episodes_done}")
        if json.loads((d / "summary.json").read_text())["stopped"] != "done":
            problems.append(f"{how}: summary says {(d / 'summary.json').read_text()[:100]}")
        for name in ("policy_best.npz", "policy_last.npz"):
            from kiloforge.policies import load_policy

            load_policy(d / name)  # raises if missing or damaged
        left = _run_files(d)
        if left:
            problems.append(f"temporaries left: {left}")
    return TrainKillResult(signal.Signals(sig).name, moment, rc, state, how, again.returncode, episodes, problems)


def kill_trainings(root: Path, n: int, rng: np.random.Generator) -> int:
    """``n`` killed trainings (SIGKILL and SIGINT, anywhere or after the first checkpoint); prints the table;
    returns how many broke a rule."""
    import collections

    root.mkdir(parents=True, exist_ok=True)
    duration, episodes = uninterrupted_training(root)
    print(f"\none short training takes {duration:.1f} s ({episodes} episodes); killing {n}")
    table: collections.Counter = collections.Counter()
    bad = 0
    t0 = time.perf_counter()
    for i in range(n):
        sig, moment = (signal.SIGKILL, signal.SIGINT)[i % 2], ("uniform", "training")[(i // 2) % 2]
        r = kill_training(root / f"t{i}", sig, moment, rng, duration, episodes)
        table[(r.signal, r.moment, r.rc, r.state, r.how, r.rc_after)] += 1
        if not r.ok:
            bad += 1
            print(f"training {i}: {r}")
    print(f"\n{n} killed trainings in {time.perf_counter() - t0:.0f} s\n")
    print_table(("signal", "moment", "exit status", "left", "continued by", "its exit status"), table)
    print(f"\ntrainings that broke a rule: {bad}")
    return bad


def print_table(headers: tuple[str, ...], counts) -> None:
    """A markdown table of outcome tuples and how many runs had each, grouped by the first two columns."""
    print("| " + " | ".join(headers) + " | runs |")
    print("|" + "---|" * (len(headers) + 1))
    for key, k in sorted(counts.items(), key=lambda kv: (kv[0][0], kv[0][1], -kv[1])):
        print("| " + " | ".join(map(str, key)) + f" | {k} |")


def said(r: KillResult) -> str:
    """What a killed export's last line said, in short."""
    if r.signal == "SIGKILL" or r.rc == 0:
        return "-"
    for key in ("nothing written", "interrupted after writing", "interpreter start-up or exit"):
        if key in r.message:
            return key
    return r.message[:40]


def kill_exports(root: Path, n: int, rng: np.random.Generator) -> int:
    """``n`` killed exports (SIGKILL and SIGINT; anywhere, once staged, once committed); prints the table;
    returns how many broke a rule."""
    import collections

    old, new, duration = reference_sets(root)
    print(f"one export takes {duration:.2f} s; killing {n}")
    table: collections.Counter = collections.Counter()
    bad = 0
    t0 = time.perf_counter()
    for i in range(n):
        sig, moment = (signal.SIGKILL, signal.SIGINT)[i % 2], ("uniform", "publish", "commit")[(i // 2) % 3]
        r = kill_export(root / f"e{i}", old, new, sig, moment, rng, duration)
        table[(r.signal, r.moment, r.before, r.after, r.rc, said(r))] += 1
        if not r.ok:
            bad += 1
            print(f"export {i}: {r}")
    print(f"\n{n} killed exports in {time.perf_counter() - t0:.0f} s\n")
    print_table(("signal", "moment", "set right after the kill", "after recovery", "exit status", "message"), table)
    print(f"\nexports that broke a rule: {bad}")
    return bad
