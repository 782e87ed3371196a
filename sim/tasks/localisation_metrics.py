"""Cooperative localisation's episode metrics (its success is the *coverage*), besides the reward.

Per episode (arrays over E episodes of T steps):

* coverage curve: fraction of robots within the communication radius of the beacon after each step;
* time to find: the first step t (1..T) after which at least one robot is within range;
  ``T`` when no robot ever is (check ``found`` to tell the two apart);
* final coverage: mean coverage over the last 25 % of the episode (:func:`sim.metrics.final_success`);
* return: the sum of the team rewards;
* of ceiling (when the episodes' packing ceilings are given, :mod:`sim.tasks.ceiling`): final coverage
  divided by the episode's ceiling, the highest final coverage the beacon's place allows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..metrics import EpisodeSteps, Summary, final_success, summarise

final_coverage = final_success  #: localisation's name of :func:`sim.metrics.final_success`



def time_to_find(coverage: np.ndarray) -> np.ndarray:
    """(E, T) coverage → (E,) int: first step (1-based) with any robot in range, T if never.

    >>> time_to_find(np.array([[0, 0, 0.5, 0], [0, 0, 0, 0], [1, 1, 1, 1]])).tolist()
    [3, 4, 1]
    """
    c = np.asarray(coverage, np.float64)
    assert c.ndim == 2, f"coverage must be (episodes, steps), got {c.shape}"
    hit = c > 0
    return np.where(hit.any(axis=1), hit.argmax(axis=1) + 1, c.shape[1]).astype(np.int64)


@dataclass
class EpisodeMetrics(EpisodeSteps):
    """Per-episode localisation metrics (E episodes) and the coverage curves they came from."""

    success: np.ndarray  # (E, T) the coverage: fraction of robots in range after each step
    returns: np.ndarray  # (E,) sum of team rewards
    time_to_find: np.ndarray  # (E,) int steps, T when never found
    found: np.ndarray  # (E,) bool, some robot was in range at some step
    final_coverage: np.ndarray  # (E,) mean coverage over the last 25 %
    ceiling: np.ndarray | None = None  # (E,) packing ceiling of each episode (None: not computed)

    def summary(self) -> dict[str, Summary]:
        """Summaries of the scalar metrics, keyed by metric name (``of_ceiling`` and ``ceiling``
        only when the ceilings are known)."""
        s = {
            "final_coverage": summarise(self.final_coverage),
            "time_to_find": summarise(self.time_to_find),
            "found_rate": summarise(self.found.astype(np.float64)),
            "mean_coverage": summarise(self.success.mean(axis=1)),
            "return": summarise(self.returns),
        }
        if self.ceiling is not None:
            s["of_ceiling"] = summarise(self.final_coverage / self.ceiling)
            s["ceiling"] = summarise(self.ceiling)
        return s

    def per_episode(self, key: str) -> np.ndarray:
        """(E,) values of one metric (``return``, ``final_coverage``, ``mean_coverage``, ``time_to_find``, ``found_rate``)."""
        return {"return": self.returns, "final_coverage": self.final_coverage, "mean_coverage": self.success.mean(axis=1),
                "time_to_find": self.time_to_find.astype(np.float64), "found_rate": self.found.astype(np.float64)}[key]

    def to_dict(self, per_episode: bool = True) -> dict:
        """JSON-ready: summaries, plus per-episode values when asked."""
        d: dict = {"episodes": self.episodes, "steps": self.steps,
                   "summary": {k: v.to_dict() for k, v in self.summary().items()}}
        if per_episode:
            d["per_episode"] = {
                "final_coverage": self.final_coverage.tolist(),
                "time_to_find": self.time_to_find.tolist(),
                "found": self.found.tolist(),
                "return": self.returns.tolist(),
            }
            if self.ceiling is not None:
                d["per_episode"]["ceiling"] = self.ceiling.tolist()
        return d


def episode_metrics(rewards: np.ndarray, coverage: np.ndarray, ceiling: np.ndarray | None = None) -> EpisodeMetrics:
    """Metrics from per-step team rewards (E, T) and coverage (E, T); ``ceiling`` (E,): each
    episode's packing ceiling, when known.

    >>> from sim.metrics import compare
    >>> from sim.tasks.localisation import Localisation
    >>> m = episode_metrics(np.zeros((2, 4)), np.array([[0, 0.5, 1, 1], [0, 0, 0, 0.5]]))
    >>> print(compare({"demo": m}, Localisation().columns))  # doctest: +NORMALIZE_WHITESPACE
    policy  final cov      mean cov       steps to find   found          return         episodes
    demo    0.750 ± 3.176  0.375 ± 3.176  3.000 ± 12.706  1.000 ± 0.000  0.000 ± 0.000  2
    """
    r = np.asarray(rewards, np.float64)
    c = np.asarray(coverage, np.float64)
    assert r.shape == c.shape and r.ndim == 2, f"rewards {r.shape} and coverage {c.shape} must both be (E, T)"
    if ceiling is not None:
        ceiling = np.asarray(ceiling, np.float64)
        assert ceiling.shape == r.shape[:1] and np.all(ceiling > 0), f"ceiling must be (E,) > 0, got {ceiling.shape}"
    return EpisodeMetrics(success=c, returns=r.sum(axis=1), time_to_find=time_to_find(c),
                          found=(c > 0).any(axis=1), final_coverage=final_coverage(c), ceiling=ceiling)
