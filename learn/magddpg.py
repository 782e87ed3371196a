"""MAGDDPG (thesis §3.3, Algorithm 4): the centralised critic guides an MLP actor over the T_prev history.

* Actor μ(h | θ^μ) (:class:`learn.networks.Actor`) sees one robot's own history: the last t_prev
  (previous action, observation) tuples, oldest first, the first tuple repeated at an episode start
  (:class:`sim.history.History`, exactly what the firmware keeps); every robot runs the same weights.
* Minibatches are transitions (s, h, a, r, s', h') cut from the episode replay
  (:meth:`learn.replay.EpisodeReplay.sample`); the critic target uses μ'(h') of every robot.
* Behaviour cloning fits μ(h_t) to the demonstrator's a_t on the demonstrations' histories.

The update itself (critic, actor with inverting or clip gradients, Q-filtered BC, soft updates) is
:class:`learn.ddpg.CentralisedDDPG`'s.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from sim.config import WorldConfig
from sim.history import History

from .ddpg import A_MAX, A_MIN, CentralisedDDPG, Rows, UpdateStats, invert_gradients, np_float64, soft_update  # noqa: F401
from .networks import Actor, Critic, config_critic
from .replay import Batch, EpisodeReplay

__all__ = ["MAGDDPG", "HistoryActing", "invert_gradients", "soft_update", "UpdateStats", "A_MIN", "A_MAX"]


class MAGDDPG(CentralisedDDPG):
    """MLP actor on flat histories (..., t_prev · tuple_dim), centralised critic, the update of Algorithm 4."""

    name = "MAGDDPG"

    def __init__(self, history_dim: int, state_dim: int, n_robots: int, actor_hidden: tuple[int, ...],
                 critic_hidden: tuple[int, ...], gamma: float, tau: float, lr_actor: float, lr_critic: float,
                 reward_scale: float = 1.0, grad_clip: float = 0.0, action_gradient: str = "invert",
                 actor_robots: int = 0, make_critic: Callable[[], torch.nn.Module] | None = None,
                 t_prev: int | None = None, device: str | torch.device = "cpu", actor_others: str = "policy",
                 precision: str = "fp32") -> None:
        actor = Actor(history_dim, actor_hidden)  # drawn first, then the critic (the seeds of earlier runs)
        critic = make_critic() if make_critic is not None else Critic(state_dim, n_robots, critic_hidden)
        super().__init__(actor, critic, gamma, tau, lr_actor, lr_critic, reward_scale, grad_clip, action_gradient,
                         actor_robots, device, actor_others, precision)
        self.t_prev = t_prev

    @classmethod
    def from_config(cls, cfg: Any, world: WorldConfig, device: str | torch.device = "cpu") -> "MAGDDPG":
        """The MAGDDPG of a :class:`learn.config.TrainConfig`."""
        M = cfg.n_robots[0]
        return cls(world.history_dim(cfg.t_prev), world.state_dim(M), M, cfg.actor_hidden, cfg.critic_hidden,
                   cfg.gamma, cfg.tau, cfg.lr_actor, cfg.lr_critic, cfg.reward_scale, cfg.grad_clip,
                   cfg.action_gradient, cfg.actor_robots, lambda: config_critic(cfg, world), cfg.t_prev, device,
                   cfg.actor_others, cfg.precision)

    # --- what the experiment loop asks ----------------------------------------------------------
    @property
    def replay_t_prev(self) -> int:
        """History length the replay cuts transitions with."""
        return self.t_prev or 1

    def sample(self, replay: EpisodeReplay, n: int, rng: np.random.Generator) -> Batch:
        return replay.sample(n, rng)

    def acting(self, n_envs: int, n_robots: int, world: WorldConfig) -> "HistoryActing":
        return HistoryActing(self, world)

    @torch.no_grad()
    def act(self, h: np.ndarray) -> np.ndarray:
        """Raw (linear, unclipped) actor output for flat histories (..., history_dim), float64 NumPy."""
        return np_float64(self.actor(self.tensor(h)))

    def bc_loss(self, demos: EpisodeReplay, n: int, rng: np.random.Generator) -> torch.Tensor:
        """Mean squared error of μ(h_t) to the demonstrated a_t over n demo transitions (all robots)."""
        b = demos.sample(n, rng)
        return torch.mean((self.actor(b.h) - b.a) ** 2)

    def artifact(self, world: WorldConfig, provenance: dict):
        """The actor as a :class:`kiloforge.actors.mlp.MLPPolicy`."""
        from kiloforge.actors.mlp import MLPPolicy

        layers = self.actor.layers()
        return MLPPolicy(weights=[w for w, _, _ in layers], biases=[b for _, b, _ in layers],
                         activations=[a for _, _, a in layers], t_prev=self.t_prev, world=world, provenance=provenance)

    def describe(self) -> str:
        return f"MLP {'-'.join(map(str, self.actor.hidden))}, T_prev {self.t_prev}"

    # --- rows and actions of a minibatch of transitions -----------------------------------------
    def rows(self, b: Batch) -> Rows:
        t = self.tensor
        return Rows(s=t(b.s), a=t(b.a), r=t(b.r), s2=t(b.s2), o=t(b.o), o2=t(b.o2))

    def n_robots_of(self, b: Batch) -> int:
        return int(b.h.shape[1])

    def target_actions(self, b: Batch) -> torch.Tensor:
        return self.actor_target(self.tensor(b.h2))

    def policy_actions(self, b: Batch, sel: torch.Tensor | None, others: torch.Tensor | None = None) -> torch.Tensor:
        h = self.tensor(b.h)
        if sel is None:
            return self.actor(h)
        if others is None:
            with torch.no_grad():
                others = self.actor(h)
        a = others.clone()  # a plain tensor, so the chosen robots' rows can be written with their graph
        idx = torch.arange(h.shape[0], device=h.device)[:, None]
        a[idx, sel] = self.actor(h[idx, sel])  # gradient only through the chosen robots
        return a

    def actor_step(self, s: Any, h: Any) -> None:
        """The actor step alone on states s (N, S) and histories h (N, M, history_dim)."""
        b = Batch(s=s, h=h, a=None, r=None, s2=None, h2=None)
        with self.arithmetic():
            self.actor_step_parts([(b, False)], [Rows(s=self.tensor(s), a=None, r=None, s2=None)], len(b))


class HistoryActing:
    """What the robots of one env group feed the MLP actor: the Algorithm-4 history of each robot."""

    def __init__(self, algo: MAGDDPG, world: WorldConfig) -> None:
        self.algo = algo
        self.history = History(algo.t_prev, world.obs_dim)
        self.h: np.ndarray | None = None

    def reset(self, obs: np.ndarray) -> np.ndarray:
        """New episodes: the history is (a_0 = 0, o_0) repeated; returns that first tuple (B, M, tuple_dim)."""
        self.h = self.history.reset(obs)
        return self.history.buf[:, :, 0]

    def act(self) -> np.ndarray:
        """Raw actions (B, M, 2) float64 of the current histories."""
        return self.algo.act(self.h)

    def push(self, action: np.ndarray, obs: np.ndarray) -> None:
        """The executed action and the next observation."""
        self.h = self.history.push(action, obs)
