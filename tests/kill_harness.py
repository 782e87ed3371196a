"""Kill a command at a random moment and check what it left (tests/test_kill.py runs a few, tests/soak/kill_test.py
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
CPYTHON_START_UP = ("Could not import runpy module", "'import warnings' failed", "'import site' failed",
                    "init_import_site: Failed to import the site module")  # CPython >= 3.9, exit status 1


class NotLanded(RuntimeError):
    """Every one of MAX_DRAWS moments came after the program had finished: that kill is not counted."""


def until_landed(kill, what: str):
    """``kill(k)`` for k = 0, 1, ... (a fresh directory each) until one lands: (its result, how many did not,
    which are not counted); NotLanded after MAX_DRAWS of them."""
    for k in range(MAX_DRAWS):
        try:
            return kill(k), k
        except NotLanded:
            pass
    raise NotLanded(f"{what}: no kill landed in {MAX_DRAWS} tries of {MAX_DRAWS} draws")


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
    redraws: int  #: moments drawn again because the export had finished before the signal (or despite it)
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

    end = 1.1 * duration
    for redraws in range(MAX_DRAWS):  # draw again (from the old set) while the export ends before the signal
        d.mkdir(parents=True, exist_ok=True)
        for n, data in old.items():
            (d / n).write_bytes(data)
        proc = subprocess.Popen(export_cmd(d, 2), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        t0 = time.perf_counter()
        if moment in ("publish", "commit"):  # wait for the staging directory (or its journal), then a moment more
            t_end = time.perf_counter() + 10 * duration + 30
            while proc.poll() is None and time.perf_counter() < t_end and not _reached(d, moment):
                time.sleep(0.0002)
            # each draw again halves the window: a SIGINT that came after the program's last line is ignored
            at = time.perf_counter() + rng.uniform(0, (0.06 if moment == "publish" else 0.005) / 2 ** redraws)
        else:
            at = t0 + rng.uniform(0, end)
        while proc.poll() is None and time.perf_counter() < at:
            time.sleep(0.0002)
        if proc.poll() is None:
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=300)
            if proc.returncode != 0:
                break
        else:
            _, err = proc.communicate(timeout=300)
        end = 0.95 * (time.perf_counter() - t0)
    else:
        raise NotLanded(f"no signal landed inside the export in {MAX_DRAWS} draws")
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
            problems.append(f"a traceback: {message[-600:]}")  # its end, to see where the signal landed
        if rc == 130 and "nothing written" in message and after != "old":
            problems.append("said 'nothing written' but the new set was published")
        if rc == 130 and "interrupted after writing" in message and before != "new":
            problems.append("said it wrote the new set but did not")
    last = "interpreter start-up or exit" if interpreter else message.splitlines()[-1] if message else ""
    return KillResult(signal.Signals(sig).name, moment, rc, before, after, left, last, redraws, problems)


# --- trainings ---------------------------------------------------------------------------------------
TRAIN_TINY = ["--world", "thesis", "--robots", "2", "--history", "3", "--episode-steps", "20", "--actor-hidden", "8", "--critic-hidden",
              "16", "--n-envs", "2", "--warmup-episodes", "2", "--batch-size", "8", "--replay-size", "400",
              "--updates-per-step", "0.5", "--eval-every", "40", "--eval-episodes", "2", "--checkpoint-every", "4",
              "--threads", "1", "--quiet"]
TRAIN_EPISODES = 16  #: after the warm-up episodes
ES_TINY = ["--robots", "2", "3", "--history", "2", "--actor-hidden", "8", "--episode-steps", "20",
           "--demo-robot-episodes", "6", "--bc-updates", "20", "--bc-batch", "64", "--pairs", "2", "--eval-every", "2",
           "--eval-episodes", "2", "--eval-steps", "30", "--threads", "1", "--quiet"]
ES_GENERATIONS = 8
#: metrics columns and policy provenance fields that measure time (they differ between two identical runs)
TIMING = ("wall_s", "env_steps_per_s", "updates_per_s", "date")
DERIVED = ("policy_hash",)  #: a hash of the arrays and the whole meta, timing included (both compared without it)
POLICIES = {"magddpg": ("policy_best.npz", "policy_last.npz"),
            "es": ("policy_bc.npz", "policy_best.npz", "policy_last.npz")}
MAX_DRAWS = 8  #: kill moments drawn for one run before giving up (each miss costs a whole run)


def train_cmd(out: Path, *extra: str, algorithm: str = "magddpg", length: int | None = None) -> list[str]:
    """The short training (``length``: episodes after warm-up, or ES generations) as a command line."""
    if algorithm == "es":
        return [sys.executable, "-m", "learn", "train-es", *ES_TINY, "--generations", str(length or ES_GENERATIONS),
                "--out", str(out), *extra]
    return [sys.executable, "-m", "learn", "train", *TRAIN_TINY, "--episodes", str(length or TRAIN_EPISODES), "--out",
            str(out), *extra]


def _run_files(d: Path) -> list[str]:
    """Temporaries anywhere in a run directory."""
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.name.startswith(".") or p.name.endswith(".tmp"))


def training_phase(d: Path) -> str:
    """Which part of a training the run directory ``d`` shows (exact once the process is dead): "before first
    checkpoint", "checkpoint write" (a checkpoint temporary, or replay blocks checkpoint.pt does not name) or
    "between checkpoints"."""
    from learn.checkpoint import REPLAY_DIR, load_file

    ck = d / "checkpoint.pt"
    named: set = set()
    if ck.is_file():
        try:
            named = {b[2] for b in load_file(ck)["blocks"]}
        except Exception:  # being replaced under our feet (SIGINT runs keep going): a write in progress
            return "checkpoint write"
    tmp = d.is_dir() and any(p.name.startswith(".checkpoint.pt") for p in d.iterdir())
    blocks = d / REPLAY_DIR
    if tmp or (blocks.is_dir() and any(p.name not in named for p in blocks.iterdir())):
        return "checkpoint write"
    return "between checkpoints" if ck.is_file() else "before first checkpoint"


def policy_contents(path: Path) -> dict:
    """A policy file's arrays and its meta JSON without the timing fields (what two identical runs share)."""
    import json

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in TIMING + DERIVED}
        return [strip(v) for v in x] if isinstance(x, list) else x

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = strip(json.loads(bytes(z["meta"]).decode("utf-8"))) if "meta" in z.files else None
    return {"arrays": arrays, "meta": meta}


def metrics_rows(d: Path) -> list[dict]:
    """metrics.csv as written (text fields) without the timing columns."""
    import csv

    with open(d / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k not in TIMING} for row in csv.DictReader(f)]


def output_differences(ref: Path, d: Path, algorithm: str = "magddpg") -> list[str]:
    """How run ``d``'s final outputs differ from the uninterrupted run ``ref`` of the same seed: every policy
    array bit-identical (dtype, shape, bytes), the meta and the metrics the same except for time taken."""
    out = []
    for name in POLICIES[algorithm]:
        a, b = policy_contents(ref / name), policy_contents(d / name)
        if sorted(a["arrays"]) != sorted(b["arrays"]):
            out.append(f"{name}: arrays {sorted(b['arrays'])}, not {sorted(a['arrays'])}")
        for k in sorted(set(a["arrays"]) & set(b["arrays"])):
            x, y = a["arrays"][k], b["arrays"][k]
            if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
                out.append(f"{name}: array {k} differs")
        if a["meta"] != b["meta"]:
            out.append(f"{name}: meta differs")
    ra, rb = metrics_rows(ref), metrics_rows(d)
    if ra != rb:
        first = next((i for i, (x, y) in enumerate(zip(ra, rb)) if x != y), min(len(ra), len(rb)))
        out.append(f"metrics.csv differs from row {first} ({len(rb)} rows, uninterrupted {len(ra)})")
    return out


@dataclass
class TrainKillResult:
    signal: str
    moment: str
    rc: int
    phase: str  #: where the kill landed (:func:`training_phase`; for SIGINT, seen just before the signal)
    state: str  #: what the kill left: "checkpoint", "no checkpoint" (config.json only), "nothing"
    how: str  #: "resumed", "restarted" or "started again"
    rc_after: int
    episodes: int
    identical: bool  #: final outputs identical to the uninterrupted run's
    redraws: int  #: kill moments drawn again because the run had finished before the signal (or despite it)
    problems: list

    @property
    def ok(self) -> bool:
        return not self.problems


def uninterrupted_training(root: Path, algorithm: str = "magddpg", length: int | None = None) -> tuple[float, int, Path]:
    """How long the short training takes, how many episodes it ends with, and its run directory."""
    from learn.checkpoint import load_checkpoint

    ref = root / f"uninterrupted-{algorithm}"
    t0 = time.perf_counter()
    subprocess.run(train_cmd(ref, algorithm=algorithm, length=length), env=ENV, check=True, capture_output=True,
                   timeout=600)
    return time.perf_counter() - t0, int(load_checkpoint(ref)["counters"]["episodes"]), ref


def _signal_inside(d: Path, sig: int, moment: str, rng: np.random.Generator, duration: float, cmd: list[str]):
    """Start ``cmd`` and send ``sig`` at a moment drawn inside the run (``uniform``: from its start;
    ``training``: from its first checkpoint), drawing again (on a fresh directory) while the run ends first or
    despite the signal. Returns (process, stderr, phase, redraws); raises if no draw lands in MAX_DRAWS."""
    import shutil

    end = 1.05 * duration  # the run's expected end, measured from its start (or from the first checkpoint)
    for draw in range(MAX_DRAWS):
        shutil.rmtree(d, ignore_errors=True)
        proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        t0 = time.perf_counter()
        if moment == "training":
            while proc.poll() is None and not (d / "checkpoint.pt").exists() and time.perf_counter() - t0 < 600:
                time.sleep(0.01)
        t_from = time.perf_counter()
        at = t_from + rng.uniform(0, max(0.05, end - (t_from - t0) if draw == 0 else end))
        while proc.poll() is None and time.perf_counter() < at:
            time.sleep(0.002)
        if proc.poll() is None:
            phase = training_phase(d) if sig != signal.SIGKILL else ""
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=600)
            if proc.returncode != 0:
                return proc, err, phase or training_phase(d), draw
        else:
            proc.communicate(timeout=600)
        end = 0.95 * (time.perf_counter() - t_from)  # from here on, draw inside what this run took
    raise NotLanded(f"no kill landed inside the run in {MAX_DRAWS} draws")


def kill_training(d: Path, sig: int, moment: str, rng: np.random.Generator, duration: float,
                  episodes_done: int, reference: Path | None = None, algorithm: str = "magddpg",
                  length: int | None = None) -> TrainKillResult:
    """Start a short training in ``d``, send ``sig`` at a random moment inside the run (``uniform``: anywhere;
    ``training``: after its first checkpoint; drawn again while the run ends first), then continue it the
    documented way (``--resume``, which restarts a run without a checkpoint; the plain command if nothing was
    written yet); it must finish with the uninterrupted run's ``episodes_done`` episodes, its policies and no
    temporaries, and (``reference``: the uninterrupted run) with outputs identical to it."""
    import json

    from learn.checkpoint import load_checkpoint

    cmd = train_cmd(d, algorithm=algorithm, length=length)
    proc, err, phase, redraws = _signal_inside(d, sig, moment, rng, duration, cmd)
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
        how, again = "started again", subprocess.run(cmd, env=ENV, capture_output=True, timeout=600)
    else:
        how = "resumed" if state == "checkpoint" else "restarted"
        again = subprocess.run(train_cmd(d, "--resume", algorithm=algorithm, length=length), env=ENV,
                               capture_output=True, timeout=600)
    episodes, identical = -1, False
    if again.returncode != 0:
        problems.append(f"{how}: exit {again.returncode}: {again.stderr.decode()[-400:]}")
    else:
        episodes = int(load_checkpoint(d)["counters"]["episodes"])
        if episodes != episodes_done:
            problems.append(f"{how}: {episodes} episodes, not {episodes_done}")
        if json.loads((d / "summary.json").read_text())["stopped"] != "done":
            problems.append(f"{how}: summary says {(d / 'summary.json').read_text()[:100]}")
        from kiloforge.policies import load_policy

        for name in POLICIES[algorithm]:
            load_policy(d / name)  # raises if missing or damaged
        left = _run_files(d)
        if left:
            problems.append(f"temporaries left: {left}")
        if reference is not None:
            diff = output_differences(reference, d, algorithm)
            identical = not diff
            problems += [f"{how}: not the uninterrupted run's outputs: {x}" for x in diff]
    return TrainKillResult(signal.Signals(sig).name, moment, rc, phase, state, how, again.returncode, episodes,
                           identical, redraws, problems)


def kill_trainings(root: Path, n: int, rng: np.random.Generator, algorithm: str = "magddpg") -> int:
    """``n`` killed trainings (SIGKILL and SIGINT, anywhere or after the first checkpoint), each continued and
    compared with the uninterrupted run; prints the table; returns how many broke a rule."""
    import collections

    root.mkdir(parents=True, exist_ok=True)
    duration, episodes, ref = uninterrupted_training(root, algorithm)
    print(f"\none short {algorithm} training takes {duration:.1f} s ({episodes} episodes); killing {n}")
    table: collections.Counter = collections.Counter()
    bad = redraws = missed = 0
    t0 = time.perf_counter()
    for i in range(n):
        sig, moment = (signal.SIGKILL, signal.SIGINT)[i % 2], ("uniform", "training")[(i // 2) % 2]
        r, lost = until_landed(lambda k: kill_training(root / f"{algorithm}{i}_{k}", sig, moment, rng, duration,
                                                      episodes, ref, algorithm), f"{algorithm} training {i}")
        missed += lost
        table[(r.signal, r.moment, r.phase, r.rc, r.state, r.how, r.rc_after,
               "identical" if r.identical else "DIFFERENT")] += 1
        redraws += r.redraws
        if not r.ok:
            bad += 1
            print(f"training {i}: {r}")
    print(f"\n{n} killed {algorithm} trainings in {time.perf_counter() - t0:.0f} s; {redraws} kill moments drawn "
          f"again (the run had ended first); {missed} kills not counted (no moment of {MAX_DRAWS} landed)\n")
    print_table(("signal", "moment", "phase hit", "exit status", "left", "continued by", "its exit status",
                 "outputs vs uninterrupted"), table)
    print(f"\n{algorithm} trainings that broke a rule: {bad}")
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
    bad = redraws = missed = 0
    t0 = time.perf_counter()
    for i in range(n):
        sig, moment = (signal.SIGKILL, signal.SIGINT)[i % 2], ("uniform", "publish", "commit")[(i // 2) % 3]
        r, lost = until_landed(lambda k: kill_export(root / f"e{i}_{k}", old, new, sig, moment, rng, duration),
                               f"export {i}")
        missed += lost
        table[(r.signal, r.moment, r.before, r.after, r.rc, said(r))] += 1
        redraws += r.redraws
        if not r.ok:
            bad += 1
            print(f"export {i}: {r}")
    print(f"\n{n} killed exports in {time.perf_counter() - t0:.0f} s; {redraws} signal moments drawn again "
          f"(the export had ended first); {missed} kills not counted (no moment of {MAX_DRAWS} landed)\n")
    print_table(("signal", "moment", "set right after the kill", "after recovery", "exit status", "message"), table)
    print(f"\nexports that broke a rule: {bad}")
    return bad
