"""The learning reward: the world's team reward, or a documented credit-assignment variant (``--reward``).

The simulator pays the thesis's team reward r = scale · ((Σ_i δ_i / M)² − penalty · (1/M) Σ_i ||a_i||²)
(§4.2; δ_i = robot i within the comm radius of the target). Its square makes a robot's value depend on
how many others are in range, which is what crowding at the target is about. Options (metrics and
evaluations always report the world's reward):

``team``       the world's reward as is (thesis).
``linear``     scale · (Σ_i δ_i / M − penalty · effort): a sum of per-robot terms, each robot in range
               worth 1/M whatever the others do.
``potential``  team + w · scale · (γ Φ(s') − Φ(s)), potential-based shaping (Ng, Harada & Russell 1999:
               it leaves the optimal policies unchanged), Φ(s) = (1/M) Σ_i δ_i · (1 − d_i / R), the
               closeness of each in-range robot to the target (d_i its true distance, R the comm radius).

``local``      per robot (B, M): scale · (δ_i − penalty · ||a_i||²), robot i's own success (the task's
               ``robot_success``: in range, in the cluster, …) and effort, what robot i controls. Their mean
               is ``linear``. It needs the per-robot critic (``--critic robot``), which learns each robot's
               own value Q_i.

``extra_action_penalty`` (any option) subtracts scale · p · (1/M) Σ_i ||a_i||² more.
"""
from __future__ import annotations

import numpy as np

from sim.config import WorldConfig
from sim.motion import action_to_u8
from sim.rollout import robot_success


def potential(env) -> np.ndarray:
    """Φ(s) (B,) of the envs' current state: mean closeness to the target of the robots in range."""
    R = env.cfg.comm_radius_mm
    d = np.linalg.norm(env.pos - env.target[:, None, :], axis=-1)  # (B, M)
    return np.mean(np.where(d <= R, 1.0 - d / R, 0.0), axis=1)


class LearningReward:
    """Turns the world's reward of one env group into the reward the critic learns."""

    def __init__(self, kind: str, world: WorldConfig, gamma: float, shaping_weight: float = 1.0,
                 extra_action_penalty: float = 0.0) -> None:
        assert kind in ("team", "linear", "potential", "local"), f"unknown reward {kind!r}"
        self.kind, self.world, self.gamma = kind, world, float(gamma)
        self.w, self.extra = float(shaping_weight), float(extra_action_penalty)
        self.phi: np.ndarray | None = None

    def reset(self, env) -> None:
        """Start of a batch of episodes."""
        if self.kind == "potential":
            self.phi = potential(env)

    def __call__(self, env, reward: np.ndarray, info, action: np.ndarray) -> np.ndarray:
        """The learning reward (B,) float32 after one step with ``action`` (B, M, 2); (B, M) for ``local``."""
        scale = self.world.reward_scale
        if self.kind == "local":
            B, M = action.shape[:2]
            u = action_to_u8(action) / 255.0 if env.cfg.tick_level else np.asarray(action, np.float64)  # as executed
            effort = np.sum(u * u, axis=-1)  # (B, M) ||a_i||², as in the world's reward
            ok = robot_success(info, B, M).astype(np.float64)
            return (scale * (ok - (self.world.action_penalty + self.extra) * effort)).astype(np.float32)
        r = np.asarray(reward, np.float64)
        if self.kind == "linear":
            s = np.asarray(info["success"], np.float64)
            r = r + scale * (s - s * s)
        elif self.kind == "potential":
            phi2 = potential(env)
            r = r + self.w * scale * (self.gamma * phi2 - self.phi)
            self.phi = phi2
        if self.extra:
            effort = np.mean(np.sum(action * action, axis=-1), axis=-1)  # (B,) (1/M) Σ_i ||a_i||²
            r = r - scale * self.extra * effort
        return r.astype(np.float32)
