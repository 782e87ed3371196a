"""Episode metrics of any task from its per-step success, besides the reward.

A task's success signal is (E, T) values in [0, 1] over E episodes of T steps (:meth:`sim.tasks.Task.step_info`).
Every task reports, per episode:

* final success: the mean success over the last 25 % of the episode (the last ``ceil(T / 4)`` steps);
* mean success: the mean over the whole episode;
* return: the sum of the team rewards;
* of ceiling (when the task gives each episode an upper bound on final success): final success divided by it.

Tasks name these metrics (:attr:`sim.tasks.Task.metrics`) and may add their own (a task module holds them,
e.g. :mod:`sim.tasks.localisation_metrics`). :func:`summarise` gives mean, sample std and a 95 % confidence
half-width (Student t) over episodes; :func:`compare` prints several policies side by side.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

FINAL_FRACTION = 0.25  #: final success averages over this trailing fraction of the episode

# two-sided 95 % Student-t quantiles t_{0.975, df} for df = 1..30; beyond that 1.96 is within 2 %
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
         2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
         2.052, 2.048, 2.045, 2.042)


def final_window(steps: int, fraction: float = FINAL_FRACTION) -> int:
    """Number of trailing steps averaged by :func:`final_success` (at least 1).

    >>> final_window(200), final_window(10), final_window(1)
    (50, 3, 1)
    """
    return max(1, math.ceil(steps * fraction - 1e-9))


def final_success(success: np.ndarray, fraction: float = FINAL_FRACTION) -> np.ndarray:
    """(E, T) → (E,): a task's mean success over the last ``final_window(T)`` steps.

    >>> final_success(np.array([[0, 0, 0, 0, 0, 0, 1, 0.5]])).tolist()
    [0.75]
    """
    c = np.asarray(success, np.float64)
    assert c.ndim == 2, f"success must be (episodes, steps), got {c.shape}"
    return c[:, -final_window(c.shape[1], fraction):].mean(axis=1)


@dataclass(frozen=True)
class Summary:
    """Mean, sample standard deviation and 95 % confidence half-width over n episodes."""

    mean: float
    std: float
    ci95: float
    n: int

    def to_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "ci95": self.ci95, "n": self.n}

    def __str__(self) -> str:
        return f"{self.mean:.3f} ± {self.ci95:.3f}"


def summarise(x: np.ndarray) -> Summary:
    """Summary of a 1-D sample; std and CI are 0 for a single value.

    >>> s = summarise(np.array([1.0, 2.0, 3.0]))
    >>> (s.mean, s.std, round(s.ci95, 3), s.n)
    (2.0, 1.0, 2.484, 3)
    """
    x = np.asarray(x, np.float64).ravel()
    assert x.size >= 1, "summarise needs at least one value"
    n = int(x.size)
    if n == 1:
        return Summary(float(x[0]), 0.0, 0.0, 1)
    std = float(x.std(ddof=1))
    t = _T975[n - 2] if n - 1 <= len(_T975) else 1.96
    return Summary(float(x.mean()), std, t * std / math.sqrt(n), n)


class EpisodeSteps:
    """``episodes`` and ``steps`` of a record of E episodes of T steps whose ``success`` is an (E, T) array
    (a task's metrics, :class:`sim.rollout.RolloutResult`, the closed loop's runs)."""

    success: np.ndarray

    @property
    def episodes(self) -> int:
        return int(self.success.shape[0])

    @property
    def steps(self) -> int:
        return int(self.success.shape[1])


@runtime_checkable
class TaskMetrics(Protocol):
    """What a task's :meth:`~sim.tasks.Task.episode_metrics` returns: per-episode metrics under the task's keys."""

    episodes: int
    steps: int

    def summary(self) -> dict[str, Summary]:
        """A :class:`Summary` per metric key."""
        ...

    def per_episode(self, key: str) -> np.ndarray:
        """(E,) values of one metric."""
        ...

    def to_dict(self, per_episode: bool = True) -> dict:
        """JSON-ready: ``episodes``, ``steps``, ``summary`` and, when asked, ``per_episode``."""
        ...


@dataclass
class SuccessMetrics(EpisodeSteps):
    """Per-episode metrics of a task from its success curve: the final value (mean over the last 25 %),
    the mean over the episode and the return, under the task's keys (``final_key``, ``mean_key``)."""

    success: np.ndarray  # (E, T) the task's success after each step
    returns: np.ndarray  # (E,) sum of team rewards
    final: np.ndarray  # (E,) mean success over the last 25 %
    final_key: str = "final_success"
    mean_key: str = "mean_success"
    ceiling: np.ndarray | None = None  # no upper bound known

    def per_episode(self, key: str) -> np.ndarray:
        """(E,) values of one metric (``return``, the final or the mean key, ``of_ceiling`` with a ceiling)."""
        if key == "of_ceiling" and self.ceiling is not None:
            return self.final / self.ceiling
        return {"return": self.returns, self.final_key: self.final, self.mean_key: self.success.mean(axis=1)}[key]

    def summary(self) -> dict[str, Summary]:
        s = {self.final_key: summarise(self.final), self.mean_key: summarise(self.success.mean(axis=1)),
             "return": summarise(self.returns)}
        if self.ceiling is not None:
            s["of_ceiling"] = summarise(self.final / self.ceiling)
            s["ceiling"] = summarise(self.ceiling)
        return s

    def to_dict(self, per_episode: bool = True) -> dict:
        d: dict = {"episodes": self.episodes, "steps": self.steps,
                   "summary": {k: v.to_dict() for k, v in self.summary().items()}}
        if per_episode:
            d["per_episode"] = {self.final_key: self.final.tolist(), "return": self.returns.tolist()}
        return d


def success_metrics(rewards: np.ndarray, success: np.ndarray, final_key: str, mean_key: str,
                    ceiling: np.ndarray | None = None) -> SuccessMetrics:
    """:class:`SuccessMetrics` from per-step team rewards (E, T) and success (E, T); ``ceiling`` (E,) > 0: each
    episode's upper bound on final success, when the task has one."""
    r = np.asarray(rewards, np.float64)
    c = np.asarray(success, np.float64)
    assert r.shape == c.shape and r.ndim == 2, f"rewards {r.shape} and success {c.shape} must both be (E, T)"
    return SuccessMetrics(c, r.sum(axis=1), final_success(c), final_key, mean_key, ceiling)


def compare(table: dict, columns: tuple[tuple[str, str], ...] | None = None) -> str:
    """A text table, one row per named policy: mean ± 95 % CI of each metric (``columns``: (key, label)
    pairs, a task's :attr:`~sim.tasks.Task.columns`; default: the first entry's metric keys).

    >>> m = success_metrics(np.zeros((2, 4)), np.array([[0, 0.5, 1, 1], [0, 0, 0, 0.5]]), "final", "mean")
    >>> print(compare({"demo": m}, (("final", "final"), ("mean", "mean"), ("return", "return"))))
    ... # doctest: +NORMALIZE_WHITESPACE
    policy  final          mean           return         episodes
    demo    0.750 ± 3.176  0.375 ± 3.176  0.000 ± 0.000  2
    """
    assert table, "compare needs at least one entry"
    sums = {name: m.summary() for name, m in table.items()}
    default = tuple((k, k) for k in next(iter(sums.values())))
    cols = [(key, label) for key, label in (columns or default) if any(key in s for s in sums.values())]
    header = ["policy"] + [label for _, label in cols] + ["episodes"]
    rows = []
    for name, m in table.items():
        s = sums[name]
        rows.append([str(name)] + [str(s[key]) if key in s else "-" for key, _ in cols] + [str(m.episodes)])
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    fmt = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(header)] + [fmt(r) for r in rows])
