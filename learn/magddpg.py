"""MAGDDPG (thesis §3.3, Algorithm 4): a centralised critic guides one actor shared by all robots.

* Critic Q(s, a¹..a^M | θ^Q) sees the full state (``env.state()``) and the joint action.
* Actor μ(h | θ^μ) sees one robot's own history; every robot runs the same parameters.
* Critic target: y = r + γ Q'(s', μ'(h¹'), …, μ'(h^M')) with target networks tracking the learned
  ones by soft updates θ' ← τ θ + (1 − τ) θ'. Episodes end by time limit only (``truncated``),
  never in a terminal state, so every target bootstraps.
* Actor gradient (thesis eq. 3.1): ∇θ J ≈ 1/N Σ_j Σ_i ∇θ μ(h_j^i) ∇_{a^i} Q(s_j, a¹..a^M), the
  sum over robots coming from the shared parameters, with ∇_{a^i} Q passed through the
  inverting-gradient rule for the bounded actions (thesis §4.3.1, Hausknecht & Stone 2016).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .networks import Actor, Critic
from .replay import Batch

A_MIN, A_MAX = 0.0, 1.0  #: motor commands u_left, u_right are in [0, 1]


def invert_gradients(grad: torch.Tensor, a: torch.Tensor, a_min: float = A_MIN,
                     a_max: float = A_MAX) -> torch.Tensor:
    """Inverting gradients for a bounded action (Hausknecht & Stone 2016, thesis §4.3.1).

    ``grad`` is ∇_a Q (the direction that increases Q) at the actor's raw (linear) output ``a``:
    where it suggests increasing a it is scaled by (a_max − a)/(a_max − a_min), otherwise by
    (a − a_min)/(a_max − a_min). Gradients shrink as a approaches a bound and point back inside
    once a is beyond it. (The thesis prints the two factors; as in Hausknecht & Stone they multiply
    the gradient.)
    """
    width = a_max - a_min
    scale = torch.where(grad > 0, (a_max - a) / width, (a - a_min) / width)
    return grad * scale


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """θ' ← τ θ + (1 − τ) θ' for every parameter (buffers are copied)."""
    t_params = list(target.parameters())
    torch._foreach_lerp_(t_params, list(source.parameters()), tau)
    for tb, sb in zip(target.buffers(), source.buffers()):
        tb.copy_(sb)


@dataclass
class UpdateStats:
    critic_loss: float
    q_mean: float
    bc_pass: float = float("nan")  #: MAGRDPG with demonstrations: fraction of demo steps passing the Q-filter


class MAGDDPG:
    """Networks, target networks, optimisers and the update of Algorithm 4."""

    def __init__(self, history_dim: int, state_dim: int, n_robots: int, actor_hidden: tuple[int, ...],
                 critic_hidden: tuple[int, ...], gamma: float, tau: float, lr_actor: float,
                 lr_critic: float, reward_scale: float = 1.0) -> None:
        self.n_robots = n_robots
        self.gamma, self.tau, self.reward_scale = float(gamma), float(tau), float(reward_scale)
        self.actor = Actor(history_dim, actor_hidden)
        self.critic = Critic(state_dim, n_robots, critic_hidden)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for p in list(self.actor_target.parameters()) + list(self.critic_target.parameters()):
            p.requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr_actor, fused=True)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=lr_critic, fused=True)

    # --- acting -------------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, h: np.ndarray) -> np.ndarray:
        """Raw (linear, unclipped) actor output for flat histories (..., history_dim), float64 NumPy."""
        return self.actor(torch.as_tensor(h, dtype=torch.float32)).double().numpy()

    # --- learning -----------------------------------------------------------------------------
    def update(self, batch: Batch) -> UpdateStats:
        """One critic step, one actor step (eq. 3.1 with inverting gradients), soft target updates."""
        s, h, a, r, s2, h2 = (torch.from_numpy(x) for x in
                              (batch.s, batch.h, batch.a, batch.r, batch.s2, batch.h2))
        # critic: y = r + γ Q'(s', μ'(h')), the target actions clipped as the robots would execute them
        with torch.no_grad():
            a2 = self.actor_target(h2).clamp(A_MIN, A_MAX)  # (N, M, 2)
            y = self.reward_scale * r + self.gamma * self.critic_target(s2, a2)  # (N,)
        q = self.critic(s, a)
        critic_loss = torch.mean((q - y) ** 2)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()

        self.actor_step(s, h)
        soft_update(self.critic_target, self.critic, self.tau)
        soft_update(self.actor_target, self.actor, self.tau)
        return UpdateStats(critic_loss=float(critic_loss.detach()), q_mean=float(q.detach().mean()))

    def actor_step(self, s: torch.Tensor, h: torch.Tensor) -> None:
        """θ^μ += lr · 1/N Σ_j Σ_i ∇θ μ(h_j^i) · invert(∇_{a^i} Q(s_j, μ(h_j^1..M)))  (via Adam)."""
        a = self.actor(h)  # (N, M, 2) raw linear outputs, graph to θ^μ
        a_in = a.detach().requires_grad_(True)
        (dq_da,) = torch.autograd.grad(self.critic(s, a_in).sum(), a_in)  # (N, M, 2): per-sample ∇_a Q
        g = invert_gradients(dq_da, a_in.detach())
        self.actor_opt.zero_grad(set_to_none=True)
        a.backward(-g / a.shape[0])  # ascend J: minimise −(1/N) Σ_j Σ_i g_j^i · μ(h_j^i)
        self.actor_opt.step()

    # --- state --------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "actor_target": self.actor_target.state_dict(),
                "critic_target": self.critic_target.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        self.actor.load_state_dict(d["actor"])
        self.critic.load_state_dict(d["critic"])
        self.actor_target.load_state_dict(d["actor_target"])
        self.critic_target.load_state_dict(d["critic_target"])
        self.actor_opt.load_state_dict(d["actor_opt"])
        self.critic_opt.load_state_dict(d["critic_opt"])
