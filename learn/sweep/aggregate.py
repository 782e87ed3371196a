"""The aggregate of a sweep directory: statistics over seeds, a table, learning curves, evaluations.

Per configuration (all trials that differ only in their seed), over its *finished* trials: mean,
sample standard deviation and 95 % confidence interval (Student t, :func:`sim.metrics.summarise`)
of the best and the last evaluation's return and the task's primary metric, plus every seed's values.
Unfinished trials are listed with their current numbers but do not enter the statistics. A sweep runs one
task (:func:`learn.sweep.trial.task_spec`); its metric keys and labels name the columns.

Writes into the sweep directory::

    summary.json             the numbers (configurations, trials, evaluation)
    table.txt                the printed tables
    learning_curves.png      per configuration: mean ± 2 std over seeds (learn.plots)
    eval_reward_over_time_M.png, eval_returns_box_M.png
                             with --eval-robots: each configuration's best policies (pooled over
                             seeds) and the baselines at M robots
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import numpy as np

from kiloforge.io import write_atomic
from sim.metrics import summarise
from sim.tasks import Task

from ..config import ConfigError
from . import trial as tr
from .grid import Grid, Trial, labels

MANIFEST = "sweep.json"  #: the sweep directory's trials and the options of its latest run


def metric_columns(task: Task) -> tuple[tuple[str, str], ...]:
    """(key, label) of the numbers aggregated per configuration: best and last return and primary metric."""
    p = task.primary_metric
    label = task.metric(p).label
    return (("best_return", "best return"), ("last_return", "last return"),
            (f"best_{p}", f"best {label}"), (f"last_{p}", f"last {label}"))


def stats(values: list[float]) -> dict:
    """mean, std (ddof 1) and 95 % CI over seeds; std and CI are None for fewer than two values."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if x.size == 0:
        return {"n": 0, "mean": None, "std": None, "ci95": None}
    s = summarise(x)
    if s.n < 2:
        return {"n": 1, "mean": s.mean, "std": None, "ci95": None}
    return {"n": s.n, "mean": s.mean, "std": s.std, "ci95": [s.mean - s.ci95, s.mean + s.ci95]}


def check_one_task(sweep_dir: Path, trials: list[Trial]) -> None:
    """Refuse trials of another task than the ones the sweep directory's manifest already holds (one line)."""
    old = (tr.read_json(sweep_dir / MANIFEST) or {}).get("trials", {})
    tr.task_spec([*(t.get("config", {}) for t in old.values()), *(t.config for t in trials)])


def write_manifest(sweep_dir: Path, grid: Grid, trials: list[Trial]) -> None:
    """Add this run's trials to the sweep directory's manifest (earlier runs' trials stay, of the same task)."""
    check_one_task(sweep_dir, trials)
    path = sweep_dir / MANIFEST
    old = tr.read_json(path) or {}
    merged = dict(old.get("trials", {}))
    merged.update({t.name: t.to_dict() for t in trials})
    write_atomic(path, json.dumps({"version": 1, "latest": grid.to_dict(), "trials": merged},
                                       indent=1, sort_keys=True) + "\n")


def read_manifest(sweep_dir: Path) -> tuple[dict, list[Trial]]:
    """(options of the latest run, all trials) of a sweep directory."""
    d = tr.read_json(sweep_dir / MANIFEST)
    if d is None:
        raise ConfigError(f"'{sweep_dir}' is not a sweep directory (no readable {MANIFEST})")
    return d["latest"], [Trial.from_dict(t) for t in d["trials"].values()]


def trial_record(sweep_dir: Path, t: Trial, budget_minutes: float | None, ev: tr.EvalSpec | None,
                 primary: str) -> dict:
    """One trial's status and numbers."""
    run_dir = sweep_dir / t.name
    cfg = tr.resolve_config(t.trainer, t.preset, t.overrides)
    budget = cfg.max_minutes if budget_minutes is None else budget_minutes
    state = tr.trial_state(cfg, run_dir, budget)
    finished = state == "finished" and tr.evaluated(run_dir, ev)
    return {"name": t.name, "config_id": t.config_id, "seed": t.seed,
            "status": "finished" if finished else ("not started" if state == "new" else "unfinished"),
            **tr.trial_numbers(tr.metric_rows(run_dir), primary)}


def aggregate(sweep_dir: str | Path, log: Callable[[str], None] = print, task: str | None = None) -> dict:
    """Aggregate a sweep directory (module doc); returns what summary.json holds. ``task`` is the command line's
    ``--task`` (needed for a task file, :func:`learn.sweep.trial.sweep_task`)."""
    from ..plots import plot_learning_curves

    sweep_dir = Path(sweep_dir)
    latest, trials = read_manifest(sweep_dir)
    ev = None if latest.get("evaluation") is None else tr.EvalSpec(
        tuple(latest["evaluation"]["robots"]), latest["evaluation"]["episodes"], latest["evaluation"]["steps"],
        latest["evaluation"]["seed"])
    spec = tr.sweep_task([t.config for t in trials], task)
    primary = spec.metric(spec.primary_metric)
    columns = metric_columns(spec)
    label = labels(trials)
    records = [trial_record(sweep_dir, t, latest.get("max_minutes"), ev, primary.key) for t in trials]
    by_config: dict[str, list[tuple[Trial, dict]]] = {}
    for t, r in zip(trials, records):
        by_config.setdefault(t.config_id, []).append((t, r))

    configs = []
    curves: dict[str, list[list[dict]]] = {}
    for cid, members in by_config.items():
        members.sort(key=lambda m: m[0].seed)
        done = [(t, r) for t, r in members if r["status"] == "finished"]
        first = members[0][0]
        entry = {"config_id": cid, "label": label[cid], "trainer": first.trainer, "preset": first.preset,
                 "fields": {k: v for k, v in first.overrides.items() if k != "seed"},
                 "trials": len(members), "finished": len(done), "seeds": [t.seed for t, _ in done],
                 "metrics": {}}
        for key, _ in columns:
            entry["metrics"][key] = {**stats([r[key] for _, r in done]),
                                     "per_seed": {str(t.seed): _finite(r[key]) for t, r in done}}
        configs.append(entry)
        runs = [tr.metric_rows(sweep_dir / t.name) for t, _ in done]
        if any(runs):
            curves[label[cid]] = [r for r in runs if r]

    summary = {"sweep_dir": str(sweep_dir), "trials": [_finite_dict(r) for r in records],
               "configurations": configs, "totals": _totals(records)}
    if curves:
        plot_learning_curves(curves, sweep_dir / "learning_curves.png", success=(f"eval_{primary.key}", primary.long),
                             title="learning curves per configuration (mean ± 2 std over seeds)")
        summary["learning_curves"] = "learning_curves.png"
    text = format_tables(configs, records, label, columns, primary.key)
    if ev is not None:
        summary["evaluation"], eval_text = aggregate_evaluation(sweep_dir, trials, records, label, ev, spec)
        text += "\n\n" + eval_text
    write_atomic(sweep_dir / "summary.json", json.dumps(summary, indent=1, sort_keys=True) + "\n")
    write_atomic(sweep_dir / "table.txt", text + "\n")
    log(text)
    return summary


def _totals(records: list[dict]) -> dict:
    out = {"trials": len(records)}
    for r in records:
        out[r["status"]] = out.get(r["status"], 0) + 1
    return out


def _finite(v):
    return v if isinstance(v, (int, float)) and math.isfinite(v) else None


def _finite_dict(d: dict) -> dict:
    return {k: (_finite(v) if isinstance(v, float) else v) for k, v in d.items()}


def _cell(s: dict, digits: int) -> str:
    if s["mean"] is None:
        return "-"
    if s["std"] is None:
        return f"{s['mean']:.{digits}f}"
    lo, hi = s["ci95"]
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    fmt = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(header), fmt(["-" * w for w in widths])] + [fmt(r) for r in rows])


def format_tables(configs: list[dict], records: list[dict], label: dict[str, str],
                  columns: tuple[tuple[str, str], ...], primary: str) -> str:
    """The configuration table (mean ± std [95 % CI] over finished seeds) and the per-trial table."""
    digits = lambda key: 3 if primary in key else 2  # noqa: E731
    rows = [[c["label"], f"{c['finished']}/{c['trials']}"] + [_cell(c["metrics"][k], digits(k)) for k, _ in columns]
            for c in configs]
    head = _table(["configuration", "seeds"] + [name for _, name in columns], rows)
    per = []
    for r in sorted(records, key=lambda r: (label[r["config_id"]], r["seed"])):
        per.append([label[r["config_id"]], str(r["seed"]), r["status"]]
                   + [("-" if not math.isfinite(r[k]) else f"{r[k]:.{digits(k)}f}") for k, _ in columns]
                   + [f"{r['env_steps']:.0f}", f"{r['wall_s']:.0f}", r["name"]])
    trials = _table(["configuration", "seed", "status"] + [name for _, name in columns]
                    + ["transitions", "wall s", "run directory"], per)
    return ("per configuration, over finished seeds: mean ± std [95 % CI]\n" + head
            + "\n\nper trial\n" + trials)


def reference_baselines(task: Task) -> list[str]:
    """The baselines the evaluation table lists beside the best policies: the task's first hand-written one and its
    random one (every baseline stays in each trial's own ``evaluation/evaluation.json``)."""
    names = list(task.baselines)
    return [n for n in names if n.startswith("hand-written")][:1] + [n for n in names if n.startswith("random")]


def aggregate_evaluation(sweep_dir: Path, trials: list[Trial], records: list[dict], label: dict[str, str],
                         ev: tr.EvalSpec, task: Task) -> tuple[dict, str]:
    """Each configuration's best policies at ``ev.robots`` robots (over seeds) and the baselines."""
    from ..plots import plot_returns_box, plot_reward_over_time

    status = {r["name"]: r["status"] for r in records}
    evals: dict[str, list[tuple[Trial, dict]]] = {}
    for t in trials:
        d = tr.read_json(sweep_dir / t.name / tr.EVAL_DIR / "evaluation.json")
        if status[t.name] == "finished" and d is not None:
            evals.setdefault(t.config_id, []).append((t, d))
    out: dict = {"robots": {}, "episodes": ev.episodes, "steps": ev.steps, "seed": ev.seed}
    P = task.primary_metric
    texts = []
    for M in ev.robots:
        key = str(M)
        rows, summary = [], {}
        curves: dict[str, np.ndarray] = {}
        returns: dict[str, np.ndarray] = {}
        baselines: dict[str, dict] = {}
        for cid, members in evals.items():
            per_seed = {t.seed: d["robots"][key]["metrics"][t.name]["summary"] for t, d in members}
            entry = {name: {**stats([s[metric]["mean"] for s in per_seed.values()]),
                            "per_seed": {str(sd): s[metric]["mean"] for sd, s in per_seed.items()}}
                     for metric, name in (("return", "return"), (P, P))}
            summary[label[cid]] = entry
            rows.append([label[cid], str(len(per_seed)), _cell(entry["return"], 2), _cell(entry[P], 3)])
            curves[label[cid]] = np.array([d["robots"][key]["mean_reward_over_time"][t.name] for t, d in members])
            returns[label[cid]] = np.concatenate([d["robots"][key]["returns"][t.name] for t, d in members])
            world = members[0][1]["world"]["name"]
            for name in reference_baselines(task):  # the same episodes for every trial of a world
                baselines.setdefault(f"{name} ({world})", (members[0][1], name))
        for bname, (d, name) in baselines.items():
            s = d["robots"][key]["metrics"][name]["summary"]
            summary[bname] = {"return": s["return"], P: s[P]}
            rows.append([bname, "-", f"{s['return']['mean']:.2f} ± {s['return']['ci95']:.2f} (95 % CI, episodes)",
                         f"{s[P]['mean']:.3f} ± {s[P]['ci95']:.3f}"])
            curves[bname] = np.array([d["robots"][key]["mean_reward_over_time"][name]])
            returns[bname] = np.asarray(d["robots"][key]["returns"][name])
        out["robots"][key] = summary
        if curves:
            plot_reward_over_time(curves, sweep_dir / f"eval_reward_over_time_{M}.png",
                                  title=f"mean reward over time, best policies, {M} robots (mean over seeds)")
            plot_returns_box(returns, sweep_dir / f"eval_returns_box_{M}.png",
                             title=f"returns, best policies pooled over seeds, {M} robots, {ev.steps} steps")
        texts.append(f"evaluation of the best policies at {M} robots ({ev.episodes} episodes of {ev.steps} steps): "
                     f"mean ± std [95 % CI] over seeds of each trial's mean\n"
                     + _table(["policy", "seeds", "return", task.metric(P).long], rows))
    return out, "\n\n".join(texts)
