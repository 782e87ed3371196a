"""The robustness suite runner: a policy's primary task metric in every world variant of :mod:`sim.variants`.

    from sim.robustness import run_suite
    table = run_suite(lambda cfg: make_policy("baseline", cfg), preset("kilobot"), robots=(4, 16))
    print(table.format())

``policy_factory(world)`` builds a :class:`sim.rollout.SwarmPolicy` for a world (the baselines, a
policy artifact's actor, ...). Every variant runs the same episode seeds as the nominal world
(:func:`sim.rollout.rollout`, seed ``seed``), so spawns are paired; each row gives the task's primary metric
(its mean ± 95 % CI over episodes) and its ratio to the nominal world's mean.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Sequence

from .config import WorldConfig
from .env import SwarmEnv
from .metrics import Summary
from .rollout import SwarmPolicy, rollout
from .tasks import Task, get_task
from .variants import Randomisation, robustness_suite

Suite = dict[str, tuple[WorldConfig, "Randomisation | None"]]


@dataclass
class SuiteTable:
    """The task's primary metric per (variant, robots): ``cells[variant][robots]`` and each one's ratio to nominal."""

    robots: tuple[int, ...]
    episodes: int
    steps: int
    seed: int
    metric: str  #: the metric's key (:attr:`sim.tasks.Task.primary_metric`)
    label: str  #: the metric's name in the table
    cells: dict[str, dict[int, Summary]] = field(default_factory=dict)

    def fraction(self, variant: str, robots: int) -> float | None:
        """Mean of the metric in ``variant`` as a fraction of the nominal world's (None when that is 0)."""
        nominal = self.cells["nominal"][robots].mean
        return self.cells[variant][robots].mean / nominal if nominal > 0 else None

    def worst(self, robots: int) -> tuple[str, float | None]:
        """The variant with the smallest fraction of nominal at ``robots``, and that fraction."""
        name = min(self.cells, key=lambda v: self.fraction(v, robots) or 0.0)
        return name, self.fraction(name, robots)

    def to_dict(self) -> dict:
        return {"robots": list(self.robots), "episodes": self.episodes, "steps": self.steps, "seed": self.seed,
                self.metric: {v: {str(m): dict(s.to_dict(), fraction_of_nominal=self.fraction(v, m))
                                       for m, s in row.items()} for v, row in self.cells.items()}}

    def format(self) -> str:
        """A markdown table: one row per variant, per robot count the metric and % of nominal."""
        head = "| variant | " + " | ".join(f"{m} robots: {self.label} | % of nominal" for m in self.robots) + " |"
        lines = [head, "|---|" + "---:|---:|" * len(self.robots)]
        for v, row in self.cells.items():
            cells = " | ".join(f"{row[m]} | {_percent(self.fraction(v, m))}" for m in self.robots)
            lines.append(f"| {v} | {cells} |")
        return "\n".join(lines)


def _percent(f: float | None) -> str:
    return "n/a" if f is None else f"{100 * f:.0f} %"


def run_suite(policy_factory: Callable[[WorldConfig], SwarmPolicy], cfg: WorldConfig,
              robots: Sequence[int] = (4, 16), episodes: int = 50, steps: int | None = None, seed: int = 0,
              suite: Suite | None = None, n_envs: int | None = None, progress: bool = False,
              task: "Task | str | None" = None) -> SuiteTable:
    """Evaluate ``policy_factory(world)`` on ``task`` (default localisation) in every variant of ``suite``
    (default :func:`sim.variants.robustness_suite` of ``cfg``) at each robot count: the task's primary metric."""
    task = get_task(task)
    assert episodes >= 1, f"episodes must be >= 1, got {episodes}"
    suite = robustness_suite(cfg) if suite is None else suite
    assert "nominal" in suite, "a suite needs a 'nominal' entry (the ratios are relative to it)"
    T = cfg.episode_steps if steps is None else int(steps)
    table = SuiteTable(tuple(int(m) for m in robots), int(episodes), T, int(seed), metric=task.primary_metric,
                       label=task.metric(task.primary_metric).long)
    bar = None
    if progress:
        from kiloforge.progress import progress_bar

        bar = progress_bar(total=len(suite) * len(table.robots), unit="run", desc="robustness suite", leave=False)
    try:
        for name, (world, rand) in suite.items():
            world = dataclasses.replace(world, episode_steps=T)
            for M in table.robots:
                env = SwarmEnv(task.world_for(world, M), n_envs or min(episodes, 50), M, seed=seed, randomise=rand,
                               task=task)
                res = rollout(env, policy_factory(world), episodes, seed=seed)
                table.cells.setdefault(name, {})[M] = res.metrics().summary()[task.primary_metric]
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return table
