"""A training run directory: its files, the metrics CSV, the summary, and what may be resumed.

    config.json          the training config (its ``algorithm`` names the class; the world is in world.json)
    world.json           the WorldConfig trained in
    metrics.csv          one row per evaluation (METRIC_COLUMNS, then extra columns)
    learning_curve.png   evaluation return and the task's primary metric over transitions
    checkpoint.pt        everything needed to resume exactly, with the replay in replay/ (learn.checkpoint)
    policy_best.npz      the actor with the best evaluation return (the exporter's format)
    policy_last.npz      the latest actor
                         (which of the two is the run's result: :func:`result_policy`)
    policy_bc.npz        with a demonstrator: the behaviour-cloned actor before reinforcement learning
    demos.json           with a demonstrator: the demonstrator's and the clone's evaluation
    summary.json         final numbers: best and last evaluation, wall time, updates/s, env steps/s
    tensorboard/         with --tensorboard: every metrics row as scalars
"""
from __future__ import annotations

import csv
import functools
import io
import json
import math
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from kiloforge.io import write_atomic
from sim import compiled
from sim.tasks import Task, get_task

from .checkpoint import Checkpointer
from .config import ConfigError, ExperimentConfig, flag_name
from .runfiles import RESUME_MAY_CHANGE

_COUNTER_COLUMNS = ("env_steps", "episodes", "updates", "wall_s", "eval_return", "eval_return_std")
_TRAIN_COLUMNS = ("train_return", "critic_loss", "q_mean", "env_steps_per_s", "updates_per_s")


def metric_columns(task: "Task | str | None" = None) -> tuple[str, ...]:
    """metrics.csv's leading columns: counters, evaluation return, ``eval_<key>`` of the task's evaluation
    metrics (:attr:`sim.tasks.Task.eval_keys`), training statistics."""
    return _COUNTER_COLUMNS + tuple(f"eval_{k}" for k in get_task(task).eval_keys) + _TRAIN_COLUMNS


METRIC_COLUMNS = metric_columns()  #: localisation's
#: files a run writes (removed when a run without a checkpoint restarts from scratch)
RUN_FILES = ("config.json", "world.json", "metrics.csv", "learning_curve.png", "checkpoint.pt", "policy_best.npz",
             "policy_last.npz", "policy_bc.npz", "demos.json", "summary.json")
KEPT_DIR = "generations"  #: train-es --keep-evaluated: every evaluated generation's policy
RUN_DIRS = ("replay", "tensorboard", KEPT_DIR)


def result_policy(cfg: object) -> str:
    """The file that is a run's result: ``policy_best.npz`` (its best evaluation), except for a run started from a
    policy (``train-es --init-policy``, a fine-tune), whose result is its last, ``policy_last.npz``: its evaluations
    in the nominal world cannot see what it is tuned for (robustness), and its best is often a generation before
    the tuning took hold (docs/training.md, "Which file is a run's result")."""
    return "policy_last.npz" if getattr(cfg, "init_policy", "") else "policy_best.npz"


def run_name(cfg: ExperimentConfig) -> str:
    """CleanRL-style run name: task__experiment__seed__unixtime."""
    return f"{cfg.task_spec().name}__{cfg.exp_name}__{cfg.seed}__{int(time.time())}"


@functools.lru_cache(maxsize=1)
def git_hash() -> str:
    """The commit of the code that trains (``unknown`` outside a git checkout)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@dataclass
class Counters:
    """Progress of a run (all of it goes into checkpoints)."""

    env_steps: int = 0  # transitions collected (summed over envs and swarm sizes)
    episodes: int = 0  # episodes finished (summed over envs and swarm sizes)
    updates: int = 0  # gradient updates made
    update_debt: float = 0.0  # fractional updates owed (updates_per_step * transitions so far)
    next_eval: int = 0  # evaluate at the first episode end with env_steps >= this
    evals: int = 0
    best_return: float = -math.inf
    wall_s: float = 0.0  # wall clock spent in this run, over all sessions
    env_s: float = 0.0  # of which: acting and stepping the environments
    update_s: float = 0.0  # of which: gradient updates
    eval_s: float = 0.0  # of which: evaluations (and their logging and exports)
    checkpoint_s: float = 0.0  # of which: writing checkpoints
    update_threads: dict = field(default_factory=dict)  # updates run per torch thread count ("1": n, "2": m)
    update_threads_note: str | None = None  # why --threads 0 kept one thread (None: it did not, or was not asked)
    rows: list = field(default_factory=list)  # metrics.csv rows
    pending_returns: list = field(default_factory=list)  # training episode returns since the last evaluation
    pending_losses: list = field(default_factory=list)  # [critic loss, Q mean, BC pass] per update since then


@dataclass
class RunResult:
    run_dir: Path
    counters: Counters
    stopped: str  #: "done", "time" or "interrupted"
    signal: int = 0  #: the signal that interrupted the run (0: none)

    @property
    def exit_status(self) -> int:
        """0, or 128 + the signal number for an interrupted run (130 SIGINT, 143 SIGTERM)."""
        return 128 + self.signal if self.stopped == "interrupted" else 0


def prepare_run_dir(run_dir: Path, resume: bool, log: Callable[[str], None]) -> bool:
    """Create the run directory; returns whether to resume from its checkpoint.

    A run directory without a checkpoint (stopped before its first one) restarts from scratch with
    ``resume``; without ``resume`` an existing run is never overwritten.
    """
    has_run = (run_dir / "config.json").exists() or (run_dir / "checkpoint.pt").exists()
    if resume:
        if (run_dir / "checkpoint.pt").is_file():
            return True
        if not (run_dir / "config.json").is_file():
            raise ConfigError(f"cannot resume: '{run_dir}' holds no training run")
        log(f"{run_dir} has no checkpoint (stopped before its first one): restarting it from scratch")
        clear_run(run_dir)
        return False
    if has_run:
        extra = "" if (run_dir / "checkpoint.pt").exists() else " (without a checkpoint: --resume restarts it)"
        raise ConfigError(f"'{run_dir}' already holds a run{extra}; use --resume to continue it or choose another --out")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create run directory '{run_dir}': {e.strerror or e}") from None
    return False


def clear_run(run_dir: Path) -> None:
    """Remove a run's own files (only those), keeping config.json for the restart."""
    for name in RUN_FILES:
        if name != "config.json":
            (run_dir / name).unlink(missing_ok=True)
    for name in RUN_DIRS:
        shutil.rmtree(run_dir / name, ignore_errors=True)
    Checkpointer(run_dir).clean()


def check_resumable(saved: dict, cfg: ExperimentConfig) -> None:
    """Refuse (one line) to resume a checkpoint with a config that changes what is learned."""
    now = cfg.to_dict()
    defaults = type(cfg)().to_dict()  # fields newer than the checkpoint: their defaults ran then
    if saved.get("algorithm", now["algorithm"]) != now["algorithm"]:
        raise ConfigError(f"cannot resume a {saved.get('algorithm')} checkpoint as {now['algorithm']}")
    diff = sorted(k for k in now if k not in RESUME_MAY_CHANGE and saved.get(k, defaults[k]) != now[k])
    if diff:
        raise ConfigError(f"cannot resume with a different {', '.join(map(flag_name, diff))}; only "
                          f"{', '.join(flag_name(k) for k in RESUME_MAY_CHANGE if k in now)} may change")


def rows_to_csv(rows: list[dict], task: "Task | str | None" = None) -> str:
    """CSV of metric rows: :func:`metric_columns` of the task, then any extra columns (e.g. bc_pass) in
    first-seen order."""
    buf = io.StringIO()
    columns = metric_columns(task)
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in columns))
    w = csv.DictWriter(buf, fieldnames=list(columns) + extra, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def write_summary(run_dir: Path, cfg: ExperimentConfig, c: Counters, stopped: str, extra: dict | None = None) -> None:
    """summary.json: the counters, their rates and shares, the best and last evaluations, and ``extra`` (an
    algorithm's own fields)."""
    best = max(c.rows, key=lambda r: r["eval_return"]) if c.rows else {}

    def share(x: float) -> float | None:
        return round(x / c.wall_s, 4) if c.wall_s else None

    summary = {
        "stopped": stopped, "env_steps": c.env_steps, "episodes": c.episodes, "updates": c.updates,
        "wall_s": round(c.wall_s, 1), "env_s": round(c.env_s, 1), "update_s": round(c.update_s, 1),
        "eval_s": round(c.eval_s, 1), "checkpoint_s": round(c.checkpoint_s, 1),
        "eval_share": share(c.eval_s), "checkpoint_share": share(c.checkpoint_s),
        "env_steps_per_s": round(c.env_steps / c.env_s, 1) if c.env_s else None,
        "updates_per_s": round(c.updates / c.update_s, 1) if c.update_s else None,
        "update_threads": c.update_threads,  #: updates per torch thread count (--threads 0 measures which is faster)
        "update_threads_note": c.update_threads_note,
        "best_eval": best, "last_eval": c.rows[-1] if c.rows else {},
        "algorithm": cfg.algorithm, "seed": cfg.seed, "git": git_hash(),
        #: the simulator's hot loops ran compiled (sim/compiled.py); the rates above depend on it, nothing else does
        "sim_compiled": compiled.available(), "sim_compiled_off_because": compiled.why_not() or None,
        **(extra or {}),
    }
    write_atomic(run_dir / "summary.json", json.dumps(finite_or_none(summary), indent=2, sort_keys=True) + "\n")


def finite_or_none(obj):
    """JSON-safe copy: NaN and infinities become None (null)."""
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_or_none(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
