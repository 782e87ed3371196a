"""Aggregation: robots spread over the arena gather into one cluster. No beacon.

*Cluster.* Two robots are linked when their centres are at most :func:`link_mm` apart: two body
diameters in collision worlds (66 mm for Kilobots, which then sense each other at 33..66 mm), half the
communication radius for point robots. A cluster is a connected group of linked robots.

*Success* of a step is the fraction of robots in the largest cluster (1 when all gathered; 1/M when
none touch); the primary metric is its mean over the last quarter of the episode, like localisation's
final coverage. Team reward: ``scale * (success² - penalty · (1/M) Σ_i ||a_i||²)``, localisation's form.
Critic state: every robot's pose, normalised.

*Baselines.* :class:`ProbabilisticAggregator`, the cockroach-inspired rule of Jeanson et al. (2005) and
Garnier et al. (2005) as Kilobots can run it: walk (straight runs, random turns, away from lit walls);
a walking robot stops with a probability that grows with the neighbours it hears, a resting one
leaves with one that shrinks with them. The neighbour count comes from the robot's own RBF histogram
(the observation), rounded to an integer, so the rule uses only what the firmware has and the firmware
(actor kind ``aggregator``) follows it exactly. Parameters tuned on validation
episodes (seed 777, docs/tasks.md). And the random walk.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..baselines import COUNTER_MAX, check_fields
from ..config import ACTION_DIM, WorldConfig
from .base import BeaconlessTask, Metric


def link_mm(cfg: WorldConfig) -> float:
    """Centre distance at which two robots are in one cluster."""
    return 4.0 * cfg.robot_radius_mm if cfg.robot_radius_mm > 0 else 0.5 * cfg.comm_radius_mm


def cluster_labels(pos: np.ndarray, link: float, extent: float) -> np.ndarray:
    """(B, M) label of each robot's cluster: the smallest flat index ``env * M + i`` of its members.

    Linked pairs from :func:`sim.grid.pairs_within`, then min-label propagation with pointer jumping
    (converges in O(log diameter) rounds), all envs at once.
    """
    from .. import grid

    B, M, _ = pos.shape
    lab = np.arange(B * M)
    p = grid.pairs_within(pos, link, extent)
    keep = p.dist <= link
    a = p.env[keep].astype(np.int64) * M + p.i[keep]
    b = p.env[keep].astype(np.int64) * M + p.j[keep]
    while a.size:
        m = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    return lab.reshape(B, M)


def largest_cluster(pos: np.ndarray, link: float, extent: float) -> tuple[np.ndarray, np.ndarray]:
    """(fraction of robots in the largest cluster (B,), membership of a largest cluster (B, M) bool)."""
    B, M, _ = pos.shape
    lab = cluster_labels(pos, link, extent)
    size = np.bincount(lab.ravel(), minlength=B * M).reshape(B, M)  # size of the cluster labelled env*M + i
    best = size.max(axis=1)
    members = size.reshape(-1)[lab] == best[:, None]
    return best / M, members


class Aggregation(BeaconlessTask):
    name = "aggregation"
    version = 1
    description = "robots spread over the arena gather into one cluster (no beacon)"
    success_label = "fraction of robots in the largest cluster"
    robot_label = "in the largest cluster"
    primary_metric = "final_cluster"
    mean_metric = "mean_cluster"
    metrics = (Metric("final_cluster", "final cluster", name="final largest-cluster fraction"),
               Metric("mean_cluster", "mean cluster"),
               Metric("return", "return"))
    baselines = {"hand-written": "aggregator", "random": "random"}
    beacon = False
    features = ("wall", "rbf")

    def step_info(self, env) -> dict[str, np.ndarray]:
        frac, members = largest_cluster(env.pos, link_mm(env.cfg), env.cfg.arena_half_mm)
        return {"success": frac, "robot_success": members}

    def make_baseline(self, name: str, cfg: WorldConfig) -> Any:
        if name == "aggregator":
            return ProbabilisticAggregator(cfg)
        from ..baselines import make_policy

        return make_policy(name, cfg)


#: the neighbours n is counted up to (a robot of the largest swarm evaluated, 32, has at most 31); a table entry
#: per n in the firmware
NBR_MAX = 31
#: what the rule's parameters may be: probabilities in [0, 1], the pivots a uint8 counter, the mean run a
#: 16-bit probability 1 / run_steps (the firmware's fields; the simulator accepts the same)
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "stop_base": (0.0, 1.0), "stop_per_nbr": (0.0, 1.0), "leave_base": (0.0, 1.0), "leave_decay": (0.0, 1000.0),
    "run_steps": (1, 0xFFFF), "turn_max_steps": (1, COUNTER_MAX), "wall_turn_steps": (1, COUNTER_MAX)}


@dataclass(frozen=True)
class AggregatorParams:
    """Constants of :class:`ProbabilisticAggregator` (probabilities per control period), tuned on validation
    episodes by ``python -m tools.tune_aggregator`` (four grids; 0.923 final cluster at 16 robots, seed 777).
    Each is checked against :data:`PARAM_RANGES` (InputError naming it and its range)."""

    stop_base: float = 0.0  #: P(stop) of a walking robot that hears no neighbour
    stop_per_nbr: float = 0.2  #: ... plus this per neighbour heard (capped at 1)
    leave_base: float = 0.7  #: P(leave) of a resting robot that hears no neighbour ...
    leave_decay: float = 1.0  #: ... divided by 1 + leave_decay · n² with n neighbours heard
    run_steps: int = 60  #: mean straight run of the walk (periods, geometric)
    turn_max_steps: int = 3  #: a random turn pivots 1..this many periods
    wall_turn_steps: int = 3  #: pivot periods away from a lit wall

    def __post_init__(self) -> None:
        check_fields(self, PARAM_RANGES, "aggregator")


def per_neighbour(cfg: WorldConfig) -> float:
    """The RBF histogram's sum that one neighbour in the middle of the sensing range adds."""
    from ..events import rbf

    mid = 0.5 * (cfg.rbf_lo_mm + min(cfg.rbf_hi_mm, cfg.comm_radius_mm))
    return float(rbf(cfg, np.array([mid])).sum())


def nbr_thresholds(cfg: WorldConfig) -> np.ndarray:
    """(NBR_MAX,) float64: n >= j neighbours are heard when the RBF sum is at least ``(j - 0.5) · per_neighbour``
    (n is the sum over one neighbour's, rounded half up, at most NBR_MAX)."""
    return (np.arange(1, NBR_MAX + 1) - 0.5) * per_neighbour(cfg)


def stop_prob(p: AggregatorParams, n: np.ndarray) -> np.ndarray:
    """P(a walking robot stops) with n neighbours."""
    return np.minimum(1.0, p.stop_base + p.stop_per_nbr * np.asarray(n, np.float64))


def leave_prob(p: AggregatorParams, n: np.ndarray) -> np.ndarray:
    """P(a resting robot leaves) with n neighbours."""
    n = np.asarray(n, np.float64)
    return p.leave_base / (1.0 + p.leave_decay * n * n)


def tumble_prob(p: AggregatorParams) -> float:
    """P(an idle walking robot starts a random turn) per period (geometric runs of mean run_steps)."""
    return 1.0 / p.run_steps


class ProbabilisticAggregator:
    """The probabilistic aggregation rule (module doc), vectorised over (B envs, M robots).

    Neighbours heard n: the RBF histogram's sum over the sum one neighbour in the middle of the range adds,
    rounded half up, at most :data:`NBR_MAX` (an integer, so the firmware's tables follow it exactly:
    kiloforge/actors/aggregator.py). Its random numbers come from :meth:`draws`.
    """

    def __init__(self, cfg: WorldConfig, params: AggregatorParams | None = None) -> None:
        self.cfg, self.p = cfg, params or AggregatorParams()
        self.thresholds = nbr_thresholds(cfg)
        self.rng: np.random.Generator | None = None

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng
        shape = (n_envs, n_robots)
        self.resting = np.zeros(shape, bool)
        self.turn_left = np.zeros(shape, np.int64)  # pivot periods still to do
        self.turn_dir = np.zeros(shape, bool)  # True: left

    def neighbours(self, obs: np.ndarray) -> np.ndarray:
        """(B, M) int64 neighbours heard this period."""
        total = np.asarray(obs, np.float64)[..., self.cfg.obs_slice("rbf")].sum(axis=-1)
        return (total[..., None] >= self.thresholds).sum(-1)

    def draws(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One period's draws: uniform [0, 1) for stopping / leaving and for starting a turn, the turn's
        pivot periods (1..turn_max_steps), its direction (True: left)."""
        assert self.rng is not None, "ProbabilisticAggregator.act before reset"
        u = self.rng.random((2,) + shape)
        steps = self.rng.integers(1, self.p.turn_max_steps + 1, shape)
        return u[0], u[1], steps, self.rng.random(shape) < 0.5

    def act(self, obs: np.ndarray) -> np.ndarray:
        p = self.p
        n = self.neighbours(obs)
        u_stay, u_turn, steps, left = self.draws(n.shape)
        stop = ~self.resting & (u_stay < stop_prob(p, n))
        leave = self.resting & (u_stay < leave_prob(p, n))
        self.resting = (self.resting | stop) & ~leave
        walking = ~self.resting
        idle = walking & (self.turn_left == 0)
        wall = idle & (obs[..., self.cfg.obs_index("wall")] > 0.5)
        tumble = idle & ~wall & (u_turn < tumble_prob(p))
        self.turn_left = np.where(wall, p.wall_turn_steps, np.where(tumble, steps, self.turn_left))
        self.turn_dir = np.where(wall | tumble, left, self.turn_dir)
        turning = walking & (self.turn_left > 0)
        a = np.zeros(n.shape + (ACTION_DIM,))
        a[walking & ~turning] = 1.0
        a[..., 0] = np.where(turning & ~self.turn_dir, 1.0, a[..., 0])  # right pivot: left motor on
        a[..., 1] = np.where(turning & self.turn_dir, 1.0, a[..., 1])
        self.turn_left = np.where(turning, self.turn_left - 1, self.turn_left)
        return a
