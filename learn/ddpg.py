"""The update shared by MAGDDPG and MAGRDPG: a centralised critic guides one actor shared by all robots.

:class:`CentralisedDDPG` holds the actor, the critic, their target networks and Adam optimisers, and
makes one update on a minibatch of *parts* (samples of one swarm size, learner's or demonstrations).
The algorithms (:mod:`learn.magddpg`, :mod:`learn.magrdpg`) supply only what the actor model
changes: how a part becomes per-transition rows, and the target and online actors' actions on them.

* Critic: y = r + γ Q'(s', clip(μ'(·))) regressed by mean squared error over every row of every
  part. Episodes end by time limit only (truncated, never terminal), so every target bootstraps.
  The per-robot critic (``--critic robot``) regresses one value per robot, y_i = r_i + γ Q'_i, on the
  robots' own rewards (``--reward local``; a team reward is every robot's r_i), and the actor ascends
  the sum of the robots' values.
* Actor (thesis eqs. 3.1/3.2): ascend (1/N) Σ_j Σ_i g_j^i · μ(·_j^i), g = ∇_{a^i} Q(s_j, μ(·_j)) passed
  through ``invert`` (inverting gradients, thesis §4.3.1, Hausknecht & Stone 2016) or ``clip`` (the
  gradient of Q(s, clip(a)): zero beyond a bound). With ``actor_robots = K`` the sum over robots is
  estimated from K random robots per sample, scaled by M / K; the other robots' actions come from the
  current actor without gradient (``actor_others="policy"``: an unbiased estimate) or from the replay
  (``"replay"``: MADDPG's choice, cheaper: no forward pass of the other robots).
* Demonstration parts add ``bc_weight`` × the squared error to the demonstrated commands where the
  critic rates the demonstrated joint action above the actor's own (the Q-filter, Nair et al. 2018).
* Soft target updates θ' ← τ θ + (1 − τ) θ'.
* ``precision="bf16"``: the update's hidden layers run under a bfloat16 autocast (matrix products with
  bfloat16 inputs and float32 accumulation; 1.2-1.3x faster updates at 32 robots on an AVX-512 CPU with bf16, none
  at 4 robots: docs/speed.md); output layers, losses, gradients of the actions, parameters and Adam stay float32. Acting, the
  exported policy and behaviour cloning are float32 either way.
"""
from __future__ import annotations

import contextlib
import copy
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from .config import ACTION_GRADIENTS, PRECISIONS

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
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)
    for tb, sb in zip(target.buffers(), source.buffers()):
        tb.copy_(sb)


@dataclass
class UpdateStats:
    critic_loss: float
    q_mean: float
    bc_pass: float = float("nan")  #: with demonstrations: fraction of demo rows passing the Q-filter


@dataclass
class Rows:
    """A part as per-transition rows (N' = samples x steps per sample)."""

    s: torch.Tensor  #: (N', S)
    a: torch.Tensor | None  #: (N', M, 2) executed actions (None where only the actor step runs)
    r: torch.Tensor | None  #: (N',)
    s2: torch.Tensor | None  #: (N', S)
    o: torch.Tensor | None = None  #: (N', M, obs_dim) (critics that read observations)
    o2: torch.Tensor | None = None


class CentralisedDDPG:
    """Networks, targets, optimisers and the update; subclasses define rows and actions of a part."""

    def __init__(self, actor: nn.Module, critic: nn.Module, gamma: float, tau: float, lr_actor: float,
                 lr_critic: float, reward_scale: float = 1.0, grad_clip: float = 0.0,
                 action_gradient: str = "invert", actor_robots: int = 0, device: str | torch.device = "cpu",
                 actor_others: str = "policy", precision: str = "fp32") -> None:
        assert action_gradient in ACTION_GRADIENTS, f"unknown action_gradient {action_gradient!r}"
        assert precision in PRECISIONS, f"unknown precision {precision!r}"
        self.precision = precision
        self.device = torch.device(device)
        self.gamma, self.tau, self.reward_scale = float(gamma), float(tau), float(reward_scale)
        self.grad_clip, self.action_gradient, self.actor_robots = float(grad_clip), action_gradient, int(actor_robots)
        assert actor_others in ("policy", "replay"), f"unknown actor_others {actor_others!r}"
        self.actor_others = actor_others
        self.actor = actor.to(self.device)
        self.critic = critic.to(self.device)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for p in list(self.actor_target.parameters()) + list(self.critic_target.parameters()):
            p.requires_grad_(False)
        fused = dict(fused=True) if self.device.type in ("cpu", "cuda") else {}
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr_actor, **fused)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=lr_critic, **fused)

    # --- what an algorithm defines --------------------------------------------------------------
    def rows(self, part: Any) -> Rows:
        raise NotImplementedError

    def target_actions(self, part: Any) -> torch.Tensor:
        """Target actor's raw actions (N', M, 2) at the next states of the rows (no gradient)."""
        raise NotImplementedError

    def policy_actions(self, part: Any, sel: torch.Tensor | None, others: torch.Tensor | None = None) -> torch.Tensor:
        """Online actor's raw actions (N', M, 2), with gradient to θ^μ for the robots ``sel`` (N, K) of
        each sample (all robots when None); the other robots' entries are ``others`` (N', M, 2) when given,
        else the actor's own without gradient."""
        raise NotImplementedError

    # --- helpers --------------------------------------------------------------------------------
    def tensor(self, x: Any) -> torch.Tensor | None:
        return None if x is None else torch.as_tensor(x, dtype=torch.float32, device=self.device)

    @staticmethod
    def q(critic: nn.Module, s: torch.Tensor, a: torch.Tensor, o: torch.Tensor | None) -> torch.Tensor:
        """critic(s, a), with the observations when the rows carry them."""
        return critic(s, a) if o is None else critic(s, a, o)

    def robot_subset(self, n: int, m: int) -> torch.Tensor | None:
        """K random robots (n, K) per sample for the actor objective, or None for all of them."""
        if not self.actor_robots or self.actor_robots >= m:
            return None
        return torch.rand(n, m).argsort(dim=1)[:, :self.actor_robots].to(self.device)

    def arithmetic(self) -> contextlib.AbstractContextManager:
        """The context the update's forward passes run in: a bfloat16 autocast, or nothing (float32)."""
        if self.precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    # --- the update -----------------------------------------------------------------------------
    def update(self, batch: Any, n_demo: int = 0, bc_weight: float = 0.0, train_actor: bool = True) -> UpdateStats:
        """One update on one minibatch whose last ``n_demo`` samples are demonstrations."""
        from .replay import split

        parts = split(batch, n_demo)
        flags = [False, True] if n_demo and len(parts) == 2 else [bool(n_demo)] * len(parts)
        return self.update_parts(list(zip(parts, flags)), bc_weight, train_actor)

    def update_parts(self, parts: Sequence[tuple[Any, bool]], bc_weight: float = 0.0,
                     train_actor: bool = True) -> UpdateStats:
        """One critic step on every row of every part, one actor step (``train_actor``), soft updates.

        ``parts``: (sample, is_demonstration) pairs; samples of different swarm sizes are separate parts.
        """
        with self.arithmetic():
            return self._update_parts(parts, bc_weight, train_actor)

    def _update_parts(self, parts: Sequence[tuple[Any, bool]], bc_weight: float, train_actor: bool) -> UpdateStats:
        rows = [self.rows(p) for p, _ in parts]
        total = sum(r.s.shape[0] for r in rows)
        self.critic_opt.zero_grad(set_to_none=True)
        loss_sum = q_sum = 0.0
        for (p, _), r in zip(parts, rows):
            with torch.no_grad():
                a2 = self.target_actions(p).clamp(A_MIN, A_MAX)
                q2 = self.q(self.critic_target, r.s2, a2, r.o2)
                rew = r.r if r.r.dim() == q2.dim() else r.r[:, None]  # a team reward for every robot's value
                y = self.reward_scale * rew + self.gamma * q2
            q = self.q(self.critic, r.s, r.a, r.o)
            width = q[0].numel()  # values per row: 1, or M for the per-robot critic
            loss = torch.sum((q - y) ** 2) / (total * width)
            loss.backward()
            loss_sum += float(loss.detach())
            q_sum += float(q.detach().sum()) / width
        self.critic_opt.step()
        stats = UpdateStats(critic_loss=loss_sum, q_mean=q_sum / total)
        if train_actor:
            stats.bc_pass = self.actor_step_parts(parts, rows, total, bc_weight)
            soft_update(self.actor_target, self.actor, self.tau)
        soft_update(self.critic_target, self.critic, self.tau)
        return stats

    def actor_step_parts(self, parts: Sequence[tuple[Any, bool]], rows: Sequence[Rows], total: int,
                         bc_weight: float = 0.0) -> float:
        """θ^μ += lr · ∇θ [(1/N) Σ_j Σ_i g_j^i · μ(·_j^i) − bc terms] (via Adam); returns the Q-filter pass rate."""
        demo_rows = sum(r.s.shape[0] for (_, d), r in zip(parts, rows) if d)
        self.actor_opt.zero_grad(set_to_none=True)
        kept: list[torch.Tensor] = []
        for (p, is_demo), r in zip(parts, rows):
            m = self.n_robots_of(p)
            sel = self.robot_subset(len(p), m)
            scale = m / sel.shape[1] if sel is not None else 1.0
            others = r.a if sel is not None and self.actor_others == "replay" else None
            a_pol = self.policy_actions(p, sel, others)  # (N', M, 2), graph to θ^μ
            a_in = a_pol.detach().requires_grad_(True)
            if self.action_gradient == "clip":
                q_pol = self.q(self.critic, r.s, a_in.clamp(A_MIN, A_MAX), r.o)
                (g,) = torch.autograd.grad(q_pol.sum(), a_in)
            else:
                q_pol = self.q(self.critic, r.s, a_in, r.o)
                (dq_da,) = torch.autograd.grad(q_pol.sum(), a_in)
                g = invert_gradients(dq_da, a_in.detach())
            objective = torch.sum(a_pol * (-g)) * (scale / total)  # minimise −(1/N) Σ g · μ
            if is_demo and bc_weight > 0:
                with torch.no_grad():
                    keep = (team_value(self.q(self.critic, r.s, r.a, r.o)) > team_value(q_pol.detach())).to(a_pol.dtype)
                err = torch.sum((a_pol - r.a) ** 2, dim=(1, 2))  # (N',) over robots and motors
                objective = objective + bc_weight * scale * torch.sum(keep * err) / (demo_rows * m)
                kept.append(keep)
            objective.backward()
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.actor.parameters(), self.grad_clip)
        self.actor_opt.step()
        return float(torch.cat(kept).mean()) if kept else float("nan")

    def n_robots_of(self, part: Any) -> int:
        raise NotImplementedError

    # --- state ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "actor_target": self.actor_target.state_dict(), "critic_target": self.critic_target.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        for name in ("actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt"):
            getattr(self, name).load_state_dict(d[name])


def team_value(q: torch.Tensor) -> torch.Tensor:
    """(N',) the team's value of the rows: Q itself, or the sum of the per-robot critic's (N', M) values."""
    return q if q.dim() == 1 else q.sum(dim=1)


def np_float64(t: torch.Tensor) -> np.ndarray:
    """A tensor as a float64 NumPy array on the CPU."""
    return t.detach().to("cpu", torch.float64).numpy()
