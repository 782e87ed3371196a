"""Evaluation: deterministic episodes of a policy, task metrics, comparison with the baselines.

* :class:`Evaluator` — what the trainer calls every ``eval_every`` transitions: ``episodes``
  deterministic episodes (actions clipped to [0, 1], no noise) from fixed seeds, so successive
  evaluations of one run see the same starting positions and are directly comparable.
* :func:`evaluate_policies` — ``python -m learn evaluate``: policy artifacts and the random and
  hand-written baselines (the searcher and its crowd variant, the pusher) at several swarm sizes
  (thesis §5.1.2: 16 and 32 robots, 500 steps, 500 episodes), with the thesis's plots (mean reward
  over time, return box plots), a plot of the task's success over time, a printed table, a JSON of the numbers
  and a GIF of one episode. A task with an upper bound (localisation's packing ceiling) also gives its
  primary metric as a fraction of each episode's bound (column "of ceiling").
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from kiloforge.io import file_stem, write_atomic
from kiloforge.policies import swarm_policy
from sim.config import WorldConfig
from sim.env import SwarmEnv
from sim.metrics import TaskMetrics, compare
from sim.rollout import RolloutResult, rollout
from sim.tasks import Task, check_policy_task, get_task

MAX_EVAL_ENVS = 50  #: envs stepped together by the evaluator (memory and cache friendly)


class Evaluator:
    """Deterministic evaluation episodes of a swarm policy, always from the same seeds."""

    def __init__(self, world: WorldConfig, n_robots: int, episodes: int, seed: int, randomise: str = "none",
                 task: "Task | str | None" = None) -> None:
        from .groups import make_env

        assert episodes >= 1, f"episodes must be >= 1, got {episodes}"
        self.world, self.n_robots, self.episodes, self.seed = world, n_robots, episodes, seed
        self.task = get_task(task)
        # the largest batch that divides the episodes, so no env is simulated for nothing
        b = min(episodes, MAX_EVAL_ENVS)
        while episodes % b:
            b -= 1
        self.env = make_env(world, b, n_robots, seed, randomise, self.task)

    def __call__(self, policy) -> TaskMetrics:
        """Metrics of ``policy`` (a :class:`sim.rollout.SwarmPolicy`, e.g. :class:`LearnerPolicy`), the task's kind."""
        return rollout(self.env, policy, self.episodes, seed=self.seed).metrics()


def evaluate_sizes(evaluators: list["Evaluator"], policy) -> tuple[dict[str, float], dict[str, float]]:
    """Each evaluator (one swarm size) on a fresh ``policy()``: (mean of every metric over the sizes,
    every size's metrics as ``<metric>_m<M>`` columns — empty with a single size)."""
    per_size = {ev.n_robots: metrics_row(ev(policy()), ev.task) for ev in evaluators}
    keys = next(iter(per_size.values())).keys()
    mean = {k: float(np.mean([m[k] for m in per_size.values()])) for k in keys}
    cols = {f"{k}_m{M}": v for M, m in per_size.items() for k, v in m.items()} if len(per_size) > 1 else {}
    return mean, cols


class LearnerPolicy:
    """The learning actor as a deterministic :class:`sim.rollout.SwarmPolicy`: the robots' inputs are
    built by the algorithm's acting object (a T_prev history, or a recurrent state), fed the clipped
    action each robot executed, as in the firmware."""

    def __init__(self, algo, world: WorldConfig) -> None:
        self.algo, self.world = algo, world
        self.acting = None
        self.prev: np.ndarray | None = None

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        self.acting = self.algo.acting(n_envs, n_robots, self.world)
        self.prev = None

    def act(self, obs: np.ndarray) -> np.ndarray:
        assert self.acting is not None, "LearnerPolicy.act before reset"
        obs = np.asarray(obs, np.float32)
        if self.prev is None:
            self.acting.reset(obs)
        else:
            self.acting.push(self.prev, obs)
        a = np.clip(self.acting.act(), 0.0, 1.0)
        self.prev = a.astype(np.float32)
        return a


@dataclass
class Contender:
    """One policy of an evaluation: a name and a SwarmPolicy factory."""

    name: str
    make: Callable[[], object]


def evaluate_policies(policies: dict[str, "object"], robots: list[int], episodes: int, steps: int,
                      out_dir: Path | None, seed: int = 0, n_envs: int = 50, baselines: bool = True,
                      gif: bool = True, progress: bool = True, log: Callable[[str], None] = print,
                      task: "Task | str | None" = None) -> dict:
    """Evaluate policy artifacts (name → a float policy of any actor kind) and the task's baselines.

    All policies must share one world (the first's) and have been trained for ``task`` (default
    localisation; another is a one-line InputError). Every policy sees the same episode seeds.
    Writes to ``out_dir``: ``reward_over_time_{M}.png``, ``returns_box_{M}.png``,
    ``<task.success_plot>_{M}.png``, ``episode_{name}_{M}.gif`` (first policy), ``evaluation.json``; with ``out_dir``
    None nothing (the tables are only logged). Returns the JSON-ready results.
    """
    assert policies or baselines, "nothing to evaluate"
    task = get_task(task)
    for name, p in policies.items():
        check_policy_task(p.task_ref, task, f"policy {name}")
    worlds: dict[str, list[str]] = {}
    for name, p in policies.items():
        worlds.setdefault(p.world.to_json(), []).append(f"{name} ('{p.world.name}')")
    if len(worlds) > 1:
        raise ValueError("the policies were trained in different worlds: "
                         + "; ".join(", ".join(names) for names in worlds.values()) + "; evaluate them separately")
    first = next(iter(policies.values()), None)
    world = first.world if first is not None else None
    assert world is not None, "evaluate_policies needs at least one policy (its world is used)"
    world = WorldConfig.from_dict({**world.to_dict(), "episode_steps": steps})

    contenders: list[Contender] = [
        Contender(name, (lambda p=p: swarm_policy(p, world))) for name, p in policies.items()]
    if baselines:
        contenders += [Contender(label, (lambda b=b: task.make_baseline(b, world))) for label, b in task.baselines.items()]

    with_ceiling = task.has_ceiling(world)
    if not with_ceiling and task.no_ceiling_note(world):
        log(f"note: {task.no_ceiling_note(world)}; the 'of ceiling' column is left out")
    results: dict = {"task": {**task.ref.to_dict(), "primary_metric": task.primary_metric},
                     "world": world.to_dict(), "episodes": episodes, "steps": steps, "seed": seed,
                     "policies": {n: {"hash": p.hash, "kind": p.kind, "architecture": p.describe(),
                                      "layer_sizes": list(p.layer_sizes), "provenance": p.provenance}
                                  for n, p in policies.items()},
                     "robots": {}}
    if with_ceiling:
        results.update(task.bound_report(world))
    for M in robots:
        b = max(1, min(n_envs, episodes))
        size_world = task.world_for(world, M)  # e.g. phototaxis's anchor arena for 64 robots
        env = SwarmEnv(size_world, n_envs=b, n_robots=M, seed=seed, task=task)
        runs: dict[str, RolloutResult] = {}
        for c in contenders:
            if progress:
                log(f"evaluating {c.name} with {M} robots: {episodes} episodes of {steps} steps")
            runs[c.name] = rollout(env, c.make(), episodes, seed=seed, record=1, progress=progress)
        metrics = {n: r.metrics(ceiling=with_ceiling) for n, r in runs.items()}
        table = compare(metrics, task.columns)
        log(f"\n{M} robots, {steps} steps, {episodes} episodes (mean ± 95 % CI)\n{table}\n")
        if out_dir is not None:
            _plot_size(runs, contenders[0].name if gif and contenders else None, world, M, steps, out_dir, task)
        results["robots"][str(M)] = {
            "table": table,
            "metrics": {n: m.to_dict(per_episode=False) for n, m in metrics.items()},
            "mean_reward_over_time": {n: r.rewards.mean(axis=0).round(6).tolist() for n, r in runs.items()},
            "returns": {n: r.rewards.sum(axis=1).round(6).tolist() for n, r in runs.items()},
        }
        if size_world != world:
            results["robots"][str(M)]["world"] = size_world.to_dict()
        if with_ceiling:  # per episode, from where each run's own episodes ended
            results["robots"][str(M)]["ceiling"] = {n: m.ceiling.round(6).tolist() for n, m in metrics.items()}

    if out_dir is not None:
        write_atomic(out_dir / "evaluation.json", json.dumps(results, indent=1, sort_keys=True, allow_nan=False))
    return results


def _plot_size(runs: dict[str, RolloutResult], gif_of: str | None, world: WorldConfig, M: int, steps: int,
               out_dir: Path, task: Task) -> None:
    """One swarm size's plots in ``out_dir`` (and the GIF of contender ``gif_of``'s first episode, if any)."""
    from .plots import plot_returns_box, plot_reward_over_time
    from sim.render import animate_episode, plot_success

    plot_reward_over_time({n: r.rewards for n, r in runs.items()}, out_dir / f"reward_over_time_{M}.png",
                          title=f"mean reward over time, {M} robots ({world.name} world)")
    plot_returns_box({n: r.rewards.sum(axis=1) for n, r in runs.items()}, out_dir / f"returns_box_{M}.png",
                     title=f"returns, {M} robots, {steps} steps ({world.name} world)")
    plot_success({n: r.success for n, r in runs.items()}, out_dir / f"{task.success_plot}_{M}.png",
                 title=f"{task.name}: {task.success_label}, {M} robots", ylabel=task.success_label)
    if gif_of is not None:
        tr = runs[gif_of].trajectories
        animate_episode(tr.positions[0], tr.headings[0], None if tr.target is None else tr.target[0], tr.in_range[0],
                        world, out_dir / f"episode_{file_stem(gif_of)}_{M}.gif", title=f"{gif_of}: {M} robots",
                        label=task.robot_label)


def metrics_row(m: TaskMetrics, task: "Task | str | None" = None) -> dict[str, float]:
    """The evaluation columns of the trainer's metrics CSV: return (mean, std), then ``eval_<key>`` for each
    of the task's evaluation metrics (:attr:`sim.tasks.Task.eval_keys`)."""
    s = m.summary()
    return {"eval_return": s["return"].mean, "eval_return_std": s["return"].std,
            **{f"eval_{k}": s[k].mean for k in get_task(task).eval_keys}}


def row_summary(row: dict, task: "Task | str | None" = None) -> str:
    """The task's evaluation metrics of a metrics row as text: ``final cov 0.912, mean cov 0.701, ...``."""
    t = get_task(task)
    return ", ".join(f"{t.metric(k).label} {row[f'eval_{k}']:.3f}" for k in t.eval_keys)


def primary_column(task: "Task | str | None" = None) -> str:
    """The CSV column a trainer selects its best policy on: ``eval_<the task's primary metric>``."""
    return f"eval_{get_task(task).primary_metric}"


def success_panel(task: "Task | str | None" = None) -> tuple[str, str]:
    """(CSV column, name) of the task's primary metric, for :func:`learn.plots.plot_learning_curves`."""
    t = get_task(task)
    return primary_column(t), t.metric(t.primary_metric).long

