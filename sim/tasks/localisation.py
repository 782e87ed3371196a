"""Cooperative localisation (the thesis's task): searchers find a beacon and gather within range of it.

The beacon is a robot of its own (``cfg.emitter_uid``) that only transmits; it is a disc in collision
worlds, taped down or pushed (``cfg.emitter_mobility``). Success of a step is the *coverage*, the
fraction of searchers whose true distance to the beacon is at most the communication radius; the
team reward is the thesis's §4.2 ``scale * (coverage² - penalty · (1/M) Σ_i ||a_i||²)``. The
critic's state is the beacon's position and every robot's pose, normalised. Baselines: the
hand-written searcher, the pusher (:mod:`sim.baselines`) and the random walk; the upper bound is
the packing ceiling (:mod:`sim.tasks.ceiling`).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..config import WorldConfig
from ..kinematics import wrap_angle
from .base import Metric, Task


class Localisation(Task):
    name = "localisation"
    version = 1
    description = "searchers find a beacon and gather within communication range of it (the thesis's task)"
    success_label = "fraction of robots in range"
    robot_label = "in range"
    primary_metric = "final_coverage"
    mean_metric = "mean_coverage"
    metrics = (
        Metric("final_coverage", "final cov", name="final coverage"),
        Metric("of_ceiling", "of ceiling", bounded=True),
        Metric("mean_coverage", "mean cov"),
        Metric("time_to_find", "steps to find", "steps", higher_is_better=False),
        Metric("found_rate", "found"),
        Metric("return", "return"),
    )
    baselines = {"hand-written": "baseline", "hand-written pusher": "pusher", "random": "random"}
    beacon = True
    features = ("wall", "target", "nbr_sensing", "rbf")
    firmware = "localisation"  #: firmware_templates/tasks/localisation/
    emitter_program = "kilobot_target.c"

    def spawn(self, env) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        B, M = env.n_envs, env.n_robots
        h = env.spawn_box()
        target = np.empty((B, 2))
        pos = np.empty((B, M, 2))
        heading = np.empty((B, M))
        for e, rng in enumerate(env.init_streams):  # loop over envs: each owns its generator
            target[e] = rng.uniform(-h, h, 2)
            pos[e] = rng.uniform(-h, h, (M, 2))
            heading[e] = rng.uniform(-math.pi, math.pi, M)
        return target, pos, wrap_angle(heading)

    def step_info(self, env) -> dict[str, np.ndarray]:
        in_range = env.target_dist <= env.cfg.comm_radius_mm
        coverage = in_range.sum(axis=1) / env.n_robots
        return {"in_range": in_range, "coverage": coverage, "success": coverage, "robot_success": in_range}

    def reward(self, env, u: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        cfg = env.cfg
        cover = info["coverage"]  # (B,) Σ δ_i / M
        effort = np.sum(u * u, axis=(1, 2)) / env.n_robots  # (B,) (1/M) Σ_i ||a_i||²
        return (cfg.reward_scale * (cover * cover - cfg.action_penalty * effort)).astype(np.float32)

    def state_dim(self, cfg: WorldConfig, n_robots: int) -> int:
        return cfg.state_dim(n_robots)

    def state(self, env) -> np.ndarray:
        """Beacon xy, then each robot's x, y, φ: positions / arena_half_mm, headings / π."""
        a, B, M = env.cfg.arena_half_mm, env.n_envs, env.n_robots
        robots = np.concatenate([env.pos / a, env.heading[..., None] / math.pi], axis=-1)  # (B, M, 3)
        return np.concatenate([env.target / a, robots.reshape(B, 3 * M)], axis=1).astype(np.float32)

    def make_baseline(self, name: str, cfg: WorldConfig) -> Any:
        from ..baselines import make_policy

        return make_policy(name, cfg)

    def episode_metrics(self, cfg: WorldConfig, n_robots: int, rewards: np.ndarray, success: np.ndarray,
                        beacon: np.ndarray | None, ceiling: bool = False) -> Any:
        """:class:`sim.tasks.localisation_metrics.EpisodeMetrics`; with ``ceiling`` also final coverage as a fraction of each
        episode's packing ceiling (:mod:`sim.tasks.ceiling`, at the final beacon position)."""
        from .ceiling import episode_ceiling
        from .localisation_metrics import episode_metrics

        return episode_metrics(rewards, success, episode_ceiling(cfg, n_robots, beacon) if ceiling else None)

    def has_ceiling(self, cfg: WorldConfig) -> bool:
        """The packing ceiling (:mod:`sim.tasks.ceiling`), where its table covers the world."""
        from .ceiling import has_ceiling

        return has_ceiling(cfg)

    def no_ceiling_note(self, cfg: WorldConfig) -> str:
        return (f"no packing ceiling for the {cfg.name} world (the shipped table is for the kilobot world's bodies, "
                "range and arena)")

    def bound_report(self, cfg: WorldConfig) -> dict[str, Any]:
        """``packing``: how many robots fit in range of the beacon in the open and on average over its places
        (worlds of disc robots)."""
        from .ceiling import mean_capacity, open_capacity

        if not (cfg.collisions and cfg.robot_radius_mm > 0):
            return {}
        return {"packing": {"open_capacity": open_capacity(cfg), "mean_capacity": mean_capacity(cfg)}}
