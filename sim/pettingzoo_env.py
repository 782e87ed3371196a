"""A PettingZoo ``ParallelEnv`` around one simulated swarm (``SwarmEnv`` with a single env).

Optional extra: ``pip install kiloforge[pettingzoo]`` (pettingzoo, gymnasium). The rest of
:mod:`sim` never imports this module.

* agents ``robot_0`` … ``robot_{M-1}`` (searcher i has kilo_uid i + 1);
* observations: each robot's float observation vector (``cfg.obs_dim``: wall, target distance,
  neighbour-sensing flag, RBF histogram), a ``Box`` of float32;
* actions: ``Box(0, 1, (2,))`` motor commands (u_left, u_right); agents missing from the action
  dict stand still;
* rewards: the shared team reward of thesis §4.2, given to every agent;
* terminations are always False; truncations become True for all agents after
  ``cfg.episode_steps`` steps, and ``agents`` is then empty until :meth:`reset`;
* infos per agent: the task's team ``success`` (float), ``robot_success`` (bool: this robot counts towards
  it) and the task's other per-robot and team ``info`` entries;
* :meth:`state`: the critic's global state (target, every robot's x, y, φ; normalised);
* ``render_mode="rgb_array"``: :meth:`render` returns an (H, W, 3) uint8 frame.
"""
from __future__ import annotations

import numpy as np

from .config import ACTION_DIM, WorldConfig, preset
from .rollout import robot_success
from .tasks import Task

try:
    import gymnasium
    from pettingzoo import ParallelEnv as _ParallelEnv
except ImportError:  # optional extra
    gymnasium = None
    _ParallelEnv = object

_MISSING = "the PettingZoo wrapper needs the optional extra: pip install 'kiloforge[pettingzoo]'"


def observation_bounds(cfg: WorldConfig, n_robots: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 of one observation vector.

    >>> lo, hi = observation_bounds(preset("thesis"), 4)
    >>> lo[:3].tolist(), hi[:3].tolist(), float(hi[-1])
    ([0.0, -1.0, 0.0], [1.0, 1.0, 1.0], 0.75)
    """
    lo = np.zeros(cfg.obs_dim, np.float32)
    hi = np.ones(cfg.obs_dim, np.float32)
    if cfg.has_feature("target"):
        lo[cfg.obs_index("target")] = -1.0
    # each table entry adds at most 1 / rbf_norm to a bin
    if cfg.has_feature("rbf"):
        hi[cfg.obs_slice("rbf")] = min(max(n_robots - 1, 0), cfg.neighbour_table_size) / cfg.rbf_norm
    return lo, hi


class SwarmParallelEnv(_ParallelEnv):
    """PettingZoo parallel API over ``SwarmEnv(cfg, n_envs=1, n_robots)``; see the module docstring."""

    metadata = {"name": "kiloforge_swarm_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, cfg: WorldConfig | str = "thesis", n_robots: int = 4, seed: int | None = None,
                 render_mode: str | None = None, task: "Task | str | None" = None) -> None:
        if gymnasium is None:
            raise ImportError(_MISSING)
        from .env import SwarmEnv
        from .tasks import get_task

        task = get_task(task)
        cfg = task.world(preset(cfg) if isinstance(cfg, str) else cfg)
        assert n_robots >= 1, f"n_robots must be >= 1, got {n_robots}"
        assert render_mode in (None, "rgb_array"), f"render_mode must be None or 'rgb_array', got {render_mode!r}"
        self.cfg = cfg
        self.render_mode = render_mode
        self.env = SwarmEnv(cfg, 1, n_robots, seed=seed, task=task)
        self.possible_agents = [f"robot_{i}" for i in range(n_robots)]
        self.agents: list[str] = []
        lo, hi = observation_bounds(cfg, n_robots)
        self.observation_spaces = {a: gymnasium.spaces.Box(lo, hi, dtype=np.float32) for a in self.possible_agents}
        self.action_spaces = {a: gymnasium.spaces.Box(0.0, 1.0, (ACTION_DIM,), np.float32)
                              for a in self.possible_agents}
        self.state_space = gymnasium.spaces.Box(-1.0, 1.0, (task.state_dim(cfg, n_robots),), np.float32)
        self._last_success = np.zeros(n_robots, bool)

    def observation_space(self, agent: str):
        return self.observation_spaces[agent]

    def action_space(self, agent: str):
        return self.action_spaces[agent]

    def _split(self, obs: np.ndarray, info):
        """Per-agent observations and infos: the task's ``success`` of the team, whether this robot counts
        towards it (``robot_success``), and the task's own per-robot / team entries."""
        M = len(self.possible_agents)
        self._last_success = robot_success(info, 1, M)[0]
        team = {k: float(v[0]) for k, v in info.items() if k not in ("events", "light") and np.shape(v) == (1,)}
        per = {k: np.asarray(v)[0] for k, v in info.items() if k not in ("events", "light") and np.shape(v) == (1, M)}
        o = {a: obs[0, i].astype(np.float32) for i, a in enumerate(self.possible_agents)}
        infos = {a: {**team, **{k: v[i].item() for k, v in per.items()}} for i, a in enumerate(self.possible_agents)}
        return o, infos

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return self._split(obs, info)

    def step(self, actions: dict):
        assert self.agents, "step() after the episode ended; call reset()"
        a = np.zeros((1, len(self.possible_agents), ACTION_DIM))
        for i, name in enumerate(self.possible_agents):
            if name in actions:
                a[0, i] = np.clip(np.asarray(actions[name], np.float64).reshape(ACTION_DIM), 0.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(a)
        o, infos = self._split(obs, info)
        r = float(reward[0])
        rewards = {n: r for n in self.agents}
        terms = {n: bool(terminated[0]) for n in self.agents}
        truncs = {n: bool(truncated[0]) for n in self.agents}
        live = list(self.agents)
        if terminated[0] or truncated[0]:
            self.agents = []
        return ({n: o[n] for n in live}, rewards, terms, truncs, {n: infos[n] for n in live})

    def state(self) -> np.ndarray:
        return np.asarray(self.env.state()[0], np.float32)

    def render(self):
        if self.render_mode is None:
            return None
        from .render import render_frame

        target = None if self.env.target is None else self.env.target[0]
        return render_frame(self.env.pos[0], self.env.heading[0], target, self._last_success, self.cfg,
                            step=int(self.env.t))

    def close(self) -> None:
        pass


def parallel_env(cfg: WorldConfig | str = "thesis", n_robots: int = 4, seed: int | None = None,
                 render_mode: str | None = None, task: "Task | str | None" = None) -> SwarmParallelEnv:
    """PettingZoo-style constructor: ``parallel_env("thesis", n_robots=4)``, ``task="aggregation"``."""
    return SwarmParallelEnv(cfg, n_robots, seed, render_mode, task)
