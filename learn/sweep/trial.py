"""One sweep trial: the only place that knows how a trainer is called and what its run directory holds.

A trial is an ordinary run directory (the files of ``python -m learn train``). It is

* ``new`` when it has no checkpoint (a directory left by a run killed before its first checkpoint
  holds nothing resumable and is started again),
* ``finished`` when its ``summary.json`` says it ran all its episodes, or stopped on its time budget
  after at least ``budget`` minutes in all its sessions,
* ``resume`` otherwise: it continues from its own ``checkpoint.pt``, with what is left of its budget.

Every other module of :mod:`learn.sweep` goes through the functions here, so that moving the sweep
to another trainer means changing :func:`_trainer` and :func:`run_trial` only.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import math
import shutil
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

from sim.config import BENCHMARK_EPISODES, BENCHMARK_STEPS
from sim.tasks import DEFAULT_TASK, Task, get_task, is_task_file, recorded_task

from ..config import ConfigError

TRAINERS = ("magddpg", "magrdpg", "es")  #: values of ``--trainer``
BUDGET_SLACK_S = 1.0  #: a run stopped on time within this of its budget has used it (wall_s is rounded)
MIN_SESSION_MINUTES = 1e-3  #: a resumed run whose budget is spent still runs to its next episode end
EVAL_DIR = "evaluation"  #: the final evaluation against the baselines, inside the run directory


@dataclass(frozen=True)
class EvalSpec:
    """The optional evaluation of a trial's best policy against the baselines (``--eval-robots``)."""

    robots: tuple[int, ...]
    episodes: int = BENCHMARK_EPISODES
    steps: int = BENCHMARK_STEPS
    seed: int = 0


def task_spec(configs: Iterable[dict]) -> str:
    """The one task (``task`` field) of a sweep's trial configs; a grid mixing tasks is a one-line ConfigError,
    since the trials' metrics (each task's own) cannot be aggregated together."""
    specs = list(dict.fromkeys(str(c.get("task", DEFAULT_TASK)) for c in configs))
    if len(specs) > 1:
        raise ConfigError(f"a sweep runs one task, and this one mixes {', '.join(specs)}: their metrics cannot be "
                          "aggregated together; sweep each task into its own --out")
    return specs[0] if specs else DEFAULT_TASK


def sweep_task(configs: Iterable[dict], given: str | None = None) -> Task:
    """The task of a sweep's trials (:func:`task_spec`), for its metric keys and labels. ``given`` is the task the
    command line names; without it a task *file* the configs name is refused (a sweep directory never makes us
    import its code) with a hint to give ``--task``."""
    spec = task_spec(configs)
    if given is None:
        return recorded_task(spec, "the sweep's trials", "--task")
    task = get_task(given)
    same = spec == given if is_task_file(spec) else get_task(spec).name == task.name
    if not same:
        raise ConfigError(f"--task {given} is not the task of the sweep's trials ({spec})")
    return task


def _trainer(trainer: str):
    """(config class, presets, train function) of a trainer."""
    if trainer == "magddpg":
        from ..config import TRAIN_PRESETS, TrainConfig
        from ..train import train

        return TrainConfig, TRAIN_PRESETS, train
    if trainer == "magrdpg":
        from ..config import RECURRENT_PRESETS, RecurrentConfig
        from ..train import train

        return RecurrentConfig, RECURRENT_PRESETS, train
    if trainer == "es":
        from ..config import ES_PRESETS, ESConfig
        from ..es_train import train_es

        return ESConfig, ES_PRESETS, train_es
    raise ConfigError(f"unknown trainer '{trainer}'; choose one of {', '.join(TRAINERS)}")


def presets(trainer: str) -> dict[str, dict]:
    """The training presets of a trainer; the first is its default."""
    return _trainer(trainer)[1]


def field_types(trainer: str) -> dict[str, Any]:
    """Field name → type of the trainer's config dataclass."""
    return typing.get_type_hints(_trainer(trainer)[0])


def check_field(trainer: str, key: str, where: str) -> None:
    """A one-line error when ``key`` is not a config field of ``trainer``."""
    fields = field_types(trainer)
    if key not in fields:
        close = difflib.get_close_matches(key, fields, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        cls = _trainer(trainer)[0].__name__
        raise ConfigError(f"{where}: '{key}' is not a {cls} field of the {trainer} trainer{hint}")


def coerce_value(trainer: str, key: str, value: Any) -> Any:
    """``value`` as field ``key``'s type, in JSON form (tuples as lists); one-line error naming the field."""
    from ..config import parse_text

    cls = _trainer(trainer)[0]
    return cls.from_dict({key: parse_text(cls, key, value)}).to_dict()[key]


def resolve_config(trainer: str, preset: str, overrides: dict[str, Any]):
    """The validated config of a trial: the preset's fields, then ``overrides``."""
    cls, table, _ = _trainer(trainer)
    if preset not in table:
        raise ConfigError(f"unknown {trainer} preset '{preset}'; choose one of {', '.join(table)}")
    return cls.from_dict({**table[preset], **overrides}).validate()


def short_name(trainer: str, cfg) -> str:
    """The readable part of a trial's directory name."""
    arch = f"t{cfg.t_prev}" if hasattr(cfg, "t_prev") else f"{cfg.cell}{cfg.hidden}"
    robots = "-".join(map(str, cfg.n_robots))
    return f"{cfg.world}-m{robots}-{arch}"


def read_json(path: Path) -> dict | None:
    """A JSON file's object, or None when it is missing or unreadable (e.g. cut by a crash)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def check_compatible(trainer: str, cfg, run_dir: Path) -> None:
    """Refuse a run directory that holds a run of another configuration (budget fields may differ)."""
    from ..train import RESUME_MAY_CHANGE

    saved = read_json(run_dir / "config.json")
    if saved is None:
        return
    defaults = _trainer(trainer)[0]().to_dict()  # fields newer than the saved run had their defaults
    now = cfg.to_dict()
    diff = sorted(k for k in now if k not in RESUME_MAY_CHANGE and saved.get(k, defaults[k]) != now[k])
    if diff:
        raise ConfigError(f"'{run_dir}' holds a run with a different {', '.join(diff)}; "
                          f"remove it or choose another --out")


def trial_state(cfg, run_dir: Path, budget_minutes: float) -> str:
    """``new``, ``resume`` or ``finished`` (module doc)."""
    if not (run_dir / "checkpoint.pt").is_file():
        return "new"
    s = read_json(run_dir / "summary.json")
    if s is None:
        return "resume"
    if s.get("episodes", 0) >= cfg.total_episodes:
        return "finished"
    if budget_minutes > 0 and s.get("stopped") == "time" and (s.get("wall_s") or 0) + BUDGET_SLACK_S >= 60 * budget_minutes:
        return "finished"
    return "resume"


def evaluated(run_dir: Path, ev: EvalSpec | None) -> bool:
    """Whether the run directory holds the evaluation ``ev`` asks for (always true without one)."""
    if ev is None:
        return True
    d = read_json(run_dir / EVAL_DIR / "evaluation.json")
    return (d is not None and d.get("episodes") == ev.episodes and d.get("steps") == ev.steps
            and d.get("seed") == ev.seed and all(str(m) in d.get("robots", {}) for m in ev.robots))


def metric_rows(run_dir: Path) -> list[dict]:
    """The run's metrics.csv rows (floats); empty before its first evaluation."""
    from ..train import read_metrics

    if not (run_dir / "metrics.csv").is_file():
        return []
    return read_metrics(run_dir)


def trial_numbers(rows: list[dict], primary: str) -> dict[str, float]:
    """Best and last evaluation of a run: return and the task's ``primary`` metric (NaN without evaluations)."""
    if not rows:
        nan = float("nan")
        return {"best_return": nan, "last_return": nan, f"best_{primary}": nan, f"last_{primary}": nan,
                "env_steps": 0.0, "wall_s": 0.0}
    best = max(rows, key=lambda r: -math.inf if math.isnan(r["eval_return"]) else r["eval_return"])
    last = rows[-1]
    return {"best_return": best["eval_return"], "last_return": last["eval_return"],
            f"best_{primary}": best[f"eval_{primary}"], f"last_{primary}": last[f"eval_{primary}"],
            "env_steps": last["env_steps"], "wall_s": last["wall_s"]}


class TrialInterrupted(RuntimeError):
    """The trainer stopped on a KeyboardInterrupt; the run directory resumes from its checkpoint."""


def run_trial(trainer: str, config: dict, run_dir: str | Path, *, budget_minutes: float | None = None,
              threads: int | None = None, evaluation: EvalSpec | None = None,
              report: Callable[[dict], None] | None = None) -> dict[str, float]:
    """Train (or resume, or skip) one trial in ``run_dir``, then evaluate it if asked.

    ``config`` is the trial's config dict; ``budget_minutes`` (default: the config's ``max_minutes``)
    is the wall-clock budget over all the trial's sessions; ``report`` receives the trial's numbers
    (:func:`trial_numbers`) after every evaluation and, with ``finished: True``, at the end.
    """
    cls, _, train = _trainer(trainer)
    run_dir = Path(run_dir)
    cfg = cls.from_dict(config)
    task = cfg.task_spec()
    if threads:
        cfg = dataclasses.replace(cfg, threads=threads)
    budget = cfg.max_minutes if budget_minutes is None else budget_minutes
    report = report or (lambda _m: None)
    state = trial_state(cfg, run_dir, budget)
    if state != "finished":
        check_compatible(trainer, cfg, run_dir)
        spent = 0.0
        if state == "new" and run_dir.exists():
            shutil.rmtree(run_dir)  # killed before its first checkpoint: nothing to resume
        elif state == "resume":
            rows = metric_rows(run_dir)
            spent = rows[-1]["wall_s"] / 60 if rows else 0.0
        if budget > 0:
            cfg = dataclasses.replace(cfg, max_minutes=max(budget - spent, MIN_SESSION_MINUTES))
        seen = [0]

        def on_log(_msg: str) -> None:  # the trainers log once per evaluation, after writing metrics.csv
            rows = metric_rows(run_dir)
            if len(rows) > seen[0]:
                seen[0] = len(rows)
                report(trial_numbers(rows, task.primary_metric))

        res = train(cfg, run_dir, resume=state == "resume", progress=False, log=on_log)
        if res.stopped == "interrupted":
            raise TrialInterrupted(f"{run_dir.name} was interrupted; rerun the sweep to resume it")
    if not evaluated(run_dir, evaluation):
        evaluate_best(run_dir, evaluation, task)
    numbers = trial_numbers(metric_rows(run_dir), task.primary_metric)
    report({**numbers, "finished": True})
    return numbers


def evaluate_best(run_dir: Path, ev: EvalSpec, task: Task) -> None:
    """The trial's best policy and the baselines at ``ev.robots`` robots, into ``run_dir/evaluation``."""
    from kiloforge.policies import load_policy

    from ..evaluate import evaluate_policies

    out = run_dir / EVAL_DIR
    out.mkdir(exist_ok=True)
    evaluate_policies({run_dir.name: load_policy(run_dir / "policy_best.npz")}, list(ev.robots), ev.episodes,
                      ev.steps, out, seed=ev.seed, baselines=True, gif=False, progress=False, log=lambda _m: None,
                      task=task)
