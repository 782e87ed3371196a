"""MAGRDPG (thesis §3.4, Algorithm 5): the centralised critic guides a shared *recurrent* actor.

What the recurrent actor model changes against MAGDDPG (:mod:`learn.magddpg`; the update itself is
:class:`learn.ddpg.CentralisedDDPG`'s):

* the actor (:class:`learn.recurrent.GRUActor`, or with ``--cell lstm`` :class:`learn.recurrent.LSTMActor`)
  reads one tuple ``x_t = [a_{t−1}, o_t]`` per step and carries a recurrent state (zero at the start of an episode, ``a_0 = 0``) instead of a ``t_prev``
  history: it fits the Kilobot's SRAM whatever the memory horizon;
* minibatches are *random updates* (Hausknecht & Stone 2015, the thesis's choice): windows cut from
  stored episodes at random starts ``t_s`` (:meth:`learn.replay.EpisodeReplay.sample_windows`). Each
  window replays up to ``burn_in`` steps from a zero hidden state without loss or gradient (a window
  never reaches back before its episode's start, where the zero state is exact), then ``unroll``
  steps t_s .. t_s+U−1 where
    - the critic regresses Q(s_t, a_t) on y_t = r_t + γ Q'(s_{t+1}, μ'(x_{t+1}, h'_t)) at *every* step
      of the window (the thesis used only the last one), the target actor unrolled over the same
      window from its own zero state;
    - the actor ascends eq. 3.2, (1 / N U) Σ_j Σ_t Σ_i ∇θ μ(x^i_t, h^i_{t−1}) · g(∇_{a^i} Q(s_t, a_t)),
      back-propagated through time over the unroll (truncated BPTT);
* behaviour cloning unrolls the actor over whole demonstration episodes from the zero state, exactly
  as it runs on the robot.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from sim.config import ACTION_DIM, WorldConfig

from .ddpg import CentralisedDDPG, Rows, np_float64
from .networks import Critic, config_critic
from .recurrent import RECURRENT_ACTORS
from .replay import EpisodeReplay, Windows


class MAGRDPG(CentralisedDDPG):
    """Recurrent actor, centralised critic, their targets, optimisers and the update of Algorithm 5."""

    name = "MAGRDPG"

    def __init__(self, in_dim: int, state_dim: int, n_robots: int, hidden: int, critic_hidden: tuple[int, ...],
                 gamma: float, tau: float, lr_actor: float, lr_critic: float, reward_scale: float = 1.0,
                 burn_in: int = 8, grad_clip: float = 0.0, action_gradient: str = "invert", actor_robots: int = 0,
                 make_critic: Callable[[], torch.nn.Module] | None = None, unroll: int = 8, cell: str = "gru",
                 device: str | torch.device = "cpu", actor_others: str = "policy", precision: str = "fp32") -> None:
        assert cell in RECURRENT_ACTORS, f"unknown recurrent cell {cell!r}"
        actor = RECURRENT_ACTORS[cell](in_dim, hidden)
        critic = make_critic() if make_critic is not None else Critic(state_dim, n_robots, critic_hidden)
        super().__init__(actor, critic, gamma, tau, lr_actor, lr_critic, reward_scale, grad_clip, action_gradient,
                         actor_robots, device, actor_others, precision)
        self.burn_in, self.unroll, self.cell = int(burn_in), int(unroll), cell

    @classmethod
    def from_config(cls, cfg: Any, world: WorldConfig, device: str | torch.device = "cpu") -> "MAGRDPG":
        """The MAGRDPG of a :class:`learn.config.RecurrentConfig`."""
        M = cfg.n_robots[0]
        return cls(world.tuple_dim, world.state_dim(M), M, cfg.hidden, cfg.critic_hidden, cfg.gamma, cfg.tau,
                   cfg.lr_actor, cfg.lr_critic, cfg.reward_scale, cfg.burn_in, cfg.grad_clip, cfg.action_gradient,
                   cfg.actor_robots, lambda: config_critic(cfg, world), cfg.unroll, cfg.cell, device, cfg.actor_others,
                   cfg.precision)

    # --- what the experiment loop asks ----------------------------------------------------------
    replay_t_prev = 1

    def sample(self, replay: EpisodeReplay, n: int, rng: np.random.Generator) -> Windows:
        return replay.sample_windows(n, self.burn_in, self.unroll, rng)

    def acting(self, n_envs: int, n_robots: int, world: WorldConfig) -> "RecurrentActing":
        return RecurrentActing(self, n_envs * n_robots)

    @torch.no_grad()
    def act(self, x: np.ndarray, h: Any) -> tuple[np.ndarray, Any]:
        """Raw (linear) actions for inputs x (R, D) and states h: (float64 (R, 2), new states)."""
        a, h = self.actor.step(self.tensor(x), h)
        return np_float64(a), h

    def bc_loss(self, demos: EpisodeReplay, n: int, rng: np.random.Generator) -> torch.Tensor:
        """Mean squared error of the actor's commands to the demonstrated ones on n robot-episodes,
        unrolled over all T steps from a zero hidden state."""
        full = np.flatnonzero(demos.filled == demos.T)
        assert full.size, "no complete demonstration episode stored"
        e = full[rng.integers(0, full.size, n)]
        i = rng.integers(0, demos.M, n)
        seq = demos.tuples.reshape(-1, demos.T + 1, demos.D)[torch.from_numpy(e * demos.M + i).to(demos.device)]
        y, _ = self.actor(seq[:, :-1], self.actor.initial_state(n))  # inputs x_0 .. x_{T-1}
        return torch.mean((y - seq[:, 1:, :ACTION_DIM]) ** 2)  # a_t is stored in x_{t+1}

    def artifact(self, world: WorldConfig, provenance: dict):
        """The actor as a policy artifact of its cell's kind (:mod:`kiloforge.actors`)."""
        return self.actor.policy(world, provenance)

    def describe(self) -> str:
        return f"{self.cell.upper()} {self.actor.hidden}"

    # --- rows and actions of a minibatch of windows ---------------------------------------------
    def rows(self, w: Windows) -> Rows:
        t = self.tensor
        N, U = w.r.shape[:2]
        M = w.a.shape[2]
        o = None if w.o is None else t(w.o).reshape(N * U, M, -1)
        o2 = None if w.o2 is None else t(w.o2).reshape(N * U, M, -1)
        return Rows(s=t(w.s).reshape(N * U, -1), a=t(w.a).reshape(N * U, M, ACTION_DIM), r=t(w.r).reshape(N * U, *w.r.shape[2:]),
                    s2=t(w.s2).reshape(N * U, -1), o=o, o2=o2)

    def n_robots_of(self, w: Windows) -> int:
        return int(w.x.shape[1])

    def _unpack(self, w: Windows) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, int, int]:
        """Windows as per-robot rows X (N·M, L, D) (row n·M + i), offsets and positions of the unroll."""
        X = self.tensor(w.x)
        N, M, L, D = X.shape
        U = L - 1 - self.burn_in
        assert U >= 1 and w.r.shape[1] == U, f"window of {L} inputs does not match burn_in {self.burn_in} + unroll"
        off = torch.as_tensor(w.off, device=self.device).repeat_interleave(M)  # (N·M,)
        pos = off[:, None] + torch.arange(U, device=self.device)  # (N·M, U) positions of t_s .. t_s + U − 1
        return X.reshape(N * M, L, D), off, pos, N, M, U

    @staticmethod
    def per_step(y: torch.Tensor, N: int, M: int, U: int) -> torch.Tensor:
        """(N·M, U, 2) robot-major -> (N·U, M, 2), rows n·U + t."""
        return y.reshape(N, M, U, ACTION_DIM).permute(0, 2, 1, 3).reshape(N * U, M, ACTION_DIM)

    def target_actions(self, w: Windows) -> torch.Tensor:
        X, _, pos, N, M, U = self._unpack(w)
        a2_all, _ = self.actor_target(X, self.actor_target.initial_state(X.shape[0]))  # (N·M, L, 2)
        rows = torch.arange(X.shape[0], device=self.device)[:, None]
        return self.per_step(a2_all[rows, pos + 1], N, M, U)

    def policy_actions(self, w: Windows, sel: torch.Tensor | None, others: torch.Tensor | None = None) -> torch.Tensor:
        X, off, pos, N, M, U = self._unpack(w)
        if sel is not None and others is not None:  # rows n·U + t -> robot-major (N·M, U, 2)
            a = others.reshape(N, U, M, ACTION_DIM).permute(0, 2, 1, 3).reshape(N * M, U, ACTION_DIM).clone()
        elif sel is not None:  # the other robots' actions without gradient: one pass from the zero state
            with torch.no_grad():
                full, _ = self.actor(X, self.actor.initial_state(X.shape[0]))
            a = full[torch.arange(X.shape[0], device=self.device)[:, None], pos]  # (N·M, U, 2)
        if sel is not None:
            r = (torch.arange(N, device=self.device)[:, None] * M + sel).reshape(-1)  # chosen rows
            X, off, pos = X[r], off[r], pos[r]
        rows = torch.arange(X.shape[0], device=self.device)[:, None]
        a_raw, _ = self.actor(X[rows, pos], self.burn_in_state(X, off))  # burn-in without gradient, then BPTT
        if sel is not None:
            a[r] = a_raw
            a_raw = a
        return self.per_step(a_raw, N, M, U)

    @torch.no_grad()
    def burn_in_state(self, X: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
        """The online actor's state after replaying each row's first ``off`` inputs from zero (no gradient).

        X (R, L, D) windows, off (R,) in 0..burn_in -> (R, H).
        """
        X, off = self.tensor(X), torch.as_tensor(off, device=self.device)
        h0 = self.actor.initial_state(X.shape[0])
        if self.burn_in == 0:
            return h0
        hs = self.actor.states(X[:, :self.burn_in], h0)  # (R, B, H) state after each position
        return torch.where((off > 0)[:, None], hs[torch.arange(X.shape[0], device=self.device), (off - 1).clamp(min=0)], h0)


class RecurrentActing:
    """What the robots of one env group feed the recurrent actor: the tuple [a_prev, o] and their hidden states."""

    def __init__(self, algo: MAGRDPG, n_rows: int) -> None:
        self.algo, self.n_rows = algo, n_rows
        self.x: np.ndarray | None = None
        self.h: Any = None

    def reset(self, obs: np.ndarray) -> np.ndarray:
        """New episodes: a_0 = 0, zero hidden states; returns the first tuple (B, M, tuple_dim)."""
        self.x = np.concatenate([np.zeros(obs.shape[:2] + (ACTION_DIM,), np.float32), obs.astype(np.float32)], -1)
        self.h = self.algo.actor.initial_state(self.n_rows)
        return self.x

    def act(self) -> np.ndarray:
        B, M, D = self.x.shape
        a, self.h = self.algo.act(self.x.reshape(B * M, D), self.h)
        return a.reshape(B, M, ACTION_DIM)

    def push(self, action: np.ndarray, obs: np.ndarray) -> None:
        self.x = np.concatenate([action.astype(np.float32), obs.astype(np.float32)], -1)
