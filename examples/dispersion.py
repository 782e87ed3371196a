"""Dispersion, a complete small task in one file (docs/tasks.md walks through it).

Robots start crowded in the middle of the arena and should spread out until none hears another.
Use it as ``--task examples/dispersion.py:Dispersion`` with every command:

    python -m sim --task examples/dispersion.py:Dispersion --policy disperser --robots 16 --out runs/disp_sim
    python -m learn train-es --task examples/dispersion.py:Dispersion --demo-policy none --robots 8 16 --out runs/disp
    python -m learn evaluate --task examples/dispersion.py:Dispersion --policy runs/disp/policy_best.npz --robots 16
    python -m export --task examples/dispersion.py:Dispersion --policy runs/disp/policy_best.npz --out disp.c --verify host
    python -m export verify --task examples/dispersion.py:Dispersion --policy runs/disp/policy_best.npz --robots 16
"""
from __future__ import annotations

import math

import numpy as np

from sim.config import ACTION_DIM
from sim.tasks import Metric, TableFeature, Task

CLOSE_MM = 66  # two body diameters: a neighbour this close crowds a robot


class Crowd(TableFeature):
    """The task's own input: neighbours heard closer than CLOSE_MM, as min(n, 4) / 4 (0 alone, 1 crowded).

    Three parts that must agree: the float reference the simulator gives the actor, the integer twin the
    emulator runs, and the C the robot runs (``export --verify host`` checks the last two bit for bit).
    """

    name = "crowd"
    doc = f"neighbours heard closer than {CLOSE_MM} mm, min(n, 4) / 4"
    firmware_decl = "    uint8_t crowd_n = 0u;\n"
    firmware = f"""
    for (i = 0u; i < s->nbr_count; ++i) {{
        crowd_n = (uint8_t)(crowd_n + (s->nbr[i].dist < {CLOSE_MM}u ? 1u : 0u));
    }}
    obs[KF_OBS_CROWD] = (int8_t)(((int16_t)(crowd_n < 4u ? crowd_n : 4u) * KF_ONE) >> 2);
"""

    def reference(self, table, cfg):
        n = table.sum(table.dist_mm < CLOSE_MM)  # (robots,) close entries of each robot's table
        return (np.minimum(n, 4) / 4.0)[:, None]

    def integer(self, table, one):
        n = table.sum((table.dist_mm < CLOSE_MM).astype(np.int64))
        return ((np.minimum(n, 4) * one) >> 2)[:, None]


class Dispersion(Task):
    name = "dispersion"  # recorded in every policy trained for it
    version = 2  # 2: observes its own feature, crowd
    description = "robots start crowded and spread out until none hears another"
    success_label = "fraction of robots alone"
    robot_label = "alone"
    primary_metric = "final_alone"
    mean_metric = "mean_alone"
    metrics = (Metric("final_alone", "final alone", name="final fraction of robots alone"),
               Metric("mean_alone", "mean alone"), Metric("return", "return"))
    baselines = {"hand-written": "disperser", "random": "random"}
    beacon = False  # nothing but the robots
    features = ("wall", "crowd", "rbf")  # the observation: the lit-wall flag, its own crowd input, the RBF histogram
    own_features = (Crowd,)

    def spawn(self, env):
        """Robots uniform in the middle quarter of the arena (the env then separates overlapping discs)."""
        h = 0.25 * env.spawn_box()
        pos = np.stack([rng.uniform(-h, h, (env.n_robots, 2)) for rng in env.init_streams])
        heading = np.stack([rng.uniform(-math.pi, math.pi, env.n_robots) for rng in env.init_streams])
        return None, pos, heading

    def step_info(self, env):
        """A robot is alone when no other robot is within the communication radius."""
        d = np.linalg.norm(env.pos[:, :, None] - env.pos[:, None], axis=-1)  # (B, M, M)
        d[:, np.arange(env.n_robots), np.arange(env.n_robots)] = np.inf
        alone = d.min(axis=2) > env.cfg.comm_radius_mm
        return {"success": alone.mean(axis=1), "robot_success": alone}

    def reward(self, env, u, info):
        return info["success"].astype(np.float32)

    def state_dim(self, cfg, n_robots):
        return 3 * n_robots

    def state(self, env):
        a = env.cfg.arena_half_mm
        robots = np.concatenate([env.pos / a, env.heading[..., None] / math.pi], axis=-1)
        return robots.reshape(env.n_envs, -1).astype(np.float32)

    def make_baseline(self, name, cfg):
        if name == "disperser":
            return Disperser(cfg)
        from sim.baselines import make_policy

        return make_policy(name, cfg)


class Disperser:
    """Hand-written: while a neighbour is heard, run straight with a random pivot now and then; else stop."""

    def __init__(self, cfg):
        self.cfg = cfg

    def reset(self, n_envs, n_robots, rng):
        self.rng = rng

    def act(self, obs):
        heard = obs[..., self.cfg.obs_slice("rbf")].sum(axis=-1) > 0  # (B, M) any neighbour heard
        turn = self.rng.random(heard.shape) < 0.2
        left = self.rng.random(heard.shape) < 0.5
        a = np.zeros(heard.shape + (ACTION_DIM,))
        a[heard & ~turn] = 1.0  # straight
        a[..., 0] = np.where(heard & turn & ~left, 1.0, a[..., 0])  # pivot right
        a[..., 1] = np.where(heard & turn & left, 1.0, a[..., 1])  # pivot left
        return a
