"""MAGRDPG (thesis §3.4, Algorithm 5): the centralised critic of MAGDDPG guides a shared *recurrent* actor.

What differs from MAGDDPG (:mod:`learn.magddpg`, whose critic, soft updates, inverting gradients,
OU noise, episode replay and evaluator are reused here):

* the actor (:class:`learn.recurrent.GRUActor`, or with ``--cell lstm`` :class:`learn.recurrent.LSTMActor`)
  reads one tuple ``x_t = [a_{t−1}, o_t]`` per step and carries a recurrent state (zero at the
  start of an episode, ``a_0 = 0``) instead of a
  ``t_prev`` history: it fits the Kilobot's SRAM whatever the memory horizon;
* updates are *random updates* (Hausknecht & Stone 2015, the thesis's choice): a minibatch is
  ``batch_windows`` windows cut from stored episodes at random starts ``t_s``. Each window
  replays up to ``burn_in`` steps from a zero hidden state without loss or gradient (a window
  never reaches back before its episode's start, where the zero state is exact), then
  ``unroll`` steps t_s .. t_s+U−1 where
    - the critic regresses Q(s_t, a_t) on y_t = r_t + γ Q'(s_{t+1}, μ'(x_{t+1}, h'_t)) at *every*
      step of the window (the thesis used only the last one; the critic is feed-forward on the full
      state, so every stored transition is a valid sample), the target actor μ' unrolled over the
      same window from its own zero state;
    - the actor ascends eq. 3.2, (1 / N U) Σ_j Σ_t Σ_i ∇θ μ(x^i_t, h^i_{t−1}) · invert(∇_{a^i} Q(s_t, a_t)),
      back-propagated through time over the unroll (truncated BPTT), inverting gradients on the
      linear output as in MAGDDPG;
* everything else (noise, warm-up, soft target updates, evaluation, run directory, metrics
  columns, plots) is as in :mod:`learn.train`, so the curves of both trainers overlay.

Guidance by demonstrations (``--demo-policy searcher``, :mod:`learn.demos`): demonstrator episodes
are collected first, the actor is pretrained on them by behaviour cloning (``bc_updates``), and
then every minibatch also holds ``demo_windows`` demonstration windows: the critic learns from them,
and the actor gets, besides eq. 3.2, a behaviour-cloning term of weight ``bc_weight`` on the demo
steps where the critic rates the demonstrated joint action above its own (the Q-filter).

``python -m learn train-recurrent --robots 2 --out runs/gru2`` (wired in ``learn/__main__.py`` via
:func:`main_train_recurrent`) or ``python -m learn.magrdpg ...``.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import inspect
import json
import math
import os
import re
import sys
import time
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from kiloforge.actors.base import StatefulActor
from kiloforge.actors.recurrent import RecurrentPolicy
from kiloforge.io import write_atomic
from kiloforge.policies import save_policy
from sim.config import ACTION_DIM
from sim.config import PRESETS as WORLD_PRESETS
from sim.config import preset as world_preset
from sim.env import SwarmEnv
from sim.rollout import rollout

from .checkpoint import load_checkpoint, save_checkpoint
from .config import ConfigError
from .demos import DEMO_POLICIES, bc_pretrain, collect_demos, demonstrator
from .evaluate import Evaluator, metrics_row
from .magddpg import A_MAX, A_MIN, UpdateStats, invert_gradients, soft_update
from .networks import Critic
from .noise import OUNoise
from .recurrent import RECURRENT_ACTORS
from .replay import EpisodeReplay
from .train import Counters, finite_or_none, git_hash, prepare_run_dir, rows_to_csv, write_summary

TASK = "coop_loc"
ACTION_GRADIENTS = ("invert", "clip")  #: values of ``--action-gradient``
CHECKPOINT_VERSION = 1


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------
@dataclass
class RecurrentConfig:
    """Everything a MAGRDPG run depends on. Field docs double as ``--help`` text."""

    # --- task --------------------------------------------------------------------------------
    world: str = "thesis"  #: world preset (sim.config.PRESETS): thesis or kilobot
    n_robots: int = 2  #: robots trained together
    episode_steps: int = 0  #: control steps per episode; 0 = the world's (thesis: 200)
    # --- networks ----------------------------------------------------------------------------
    hidden: int = 32  #: units of the actor's recurrent cell (the firmware keeps them as int8 in SRAM)
    cell: str = "gru"  #: the actor's recurrent cell: gru or lstm (the thesis's MAGRDPG used an LSTM)
    critic_hidden: tuple[int, ...] = (256, 128, 64)  #: critic hidden widths (ELU), as MAGDDPG
    # --- MAGRDPG -----------------------------------------------------------------------------
    unroll: int = 8  #: T_unroll: steps per window with loss and gradient (truncated BPTT length)
    burn_in: int = 8  #: steps before them that only warm up the hidden state from zero
    batch_windows: int = 32  #: windows per minibatch (critic samples = batch_windows x unroll)
    gamma: float = 0.99  #: discount factor
    tau: float = 0.005  #: soft target update rate
    lr_critic: float = 1e-3  #: Adam learning rate of the critic
    lr_actor: float = 3e-4  #: Adam learning rate of the actor (1e-3, MAGDDPG's fast value, was less stable)
    grad_clip: float = 1.0  #: clip the actor's gradient norm to this (0 = no clipping)
    #: how ∇_a Q reaches a bounded action: invert (inverting gradients, thesis §4.3.1) or clip (the
    #: gradient of Q(s, clip(a)): zero beyond the bounds, so commands at 0 or 1 are not ratcheted inwards)
    action_gradient: str = "invert"
    replay_size: int = 200_000  #: replay memory capacity in transitions (whole episodes)
    warmup_episodes: int = 32  #: episodes (summed over envs) with the initial policy before learning
    episodes: int = 100_000  #: learning episodes (summed over envs) after the warm-up
    updates_per_step: float = 0.125  #: gradient updates per collected transition
    reward_scale: float = 1.0  #: multiplies the world's reward for learning only (metrics stay raw)
    # --- exploration (Ornstein-Uhlenbeck, per robot and motor) -------------------------------
    noise_theta: float = 0.15  #: OU mean reversion per control step
    noise_sigma: float = 0.2  #: OU noise scale per control step
    noise_mu: float = 0.0  #: OU mean
    # --- speed and bookkeeping ---------------------------------------------------------------
    n_envs: int = 16  #: environments stepped together
    threads: int = 1  #: torch CPU threads
    eval_every: int = 25_600  #: evaluate every this many transitions (at the next episode end)
    eval_episodes: int = 20  #: deterministic evaluation episodes (fixed seeds, as MAGDDPG's evaluator)
    checkpoint_every: int = 1  #: write a checkpoint every this many evaluations (0 = only at the end)
    max_minutes: float = 0.0  #: stop at the first episode end after this wall-clock time (0 = no limit)
    # --- guidance by demonstrations (learn.demos) --------------------------------------------
    demo_policy: str = "none"  #: demonstrator: none, or searcher (the hand-written searcher, turning left)
    demo_episodes: int = 1024  #: demonstrator episodes collected before training (kept all run long)
    bc_updates: int = 1500  #: behaviour-cloning steps of the actor on whole demo episodes before RL
    bc_lr: float = 3e-3  #: Adam learning rate of behaviour cloning
    demo_windows: int = 8  #: demonstration windows added to every minibatch
    bc_weight: float = 1.0  #: weight of the Q-filtered behaviour-cloning loss during RL (0 = none)
    actor_delay: int = 0  #: the first this many updates train only the critic (keeps a cloned actor intact)
    critic_pretrain: int = 0  #: critic-only updates on the demonstrations after cloning (evaluates the clone)
    seed: int = 1  #: master seed (networks, environments, noise, replay sampling, evaluation)
    exp_name: str = "gru"  #: experiment name used in the default run directory name

    def validate(self) -> "RecurrentConfig":
        """Raise :class:`ConfigError` (one line) for a bad value; return self."""
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ConfigError(msg)

        need(self.world in WORLD_PRESETS, f"world must be one of {', '.join(sorted(WORLD_PRESETS))}, got '{self.world}'")
        need(1 <= self.n_robots <= 256, f"n_robots must be in 1..256, got {self.n_robots}")
        need(self.episode_steps >= 0, f"episode_steps must be >= 0 (0 = the world's), got {self.episode_steps}")
        need(1 <= self.hidden <= 255, f"hidden must be in 1..255 (uint8 index in the firmware), got {self.hidden}")
        need(self.cell in RECURRENT_ACTORS, f"cell must be one of {', '.join(RECURRENT_ACTORS)}, got '{self.cell}'")
        need(len(self.critic_hidden) >= 1 and all(1 <= w <= 4096 for w in self.critic_hidden),
             f"critic_hidden must be one or more widths in 1..4096, got {list(self.critic_hidden)}")
        need(self.unroll >= 1, f"unroll must be >= 1, got {self.unroll}")
        need(self.burn_in >= 0, f"burn_in must be >= 0, got {self.burn_in}")
        need(self.batch_windows >= 1, f"batch_windows must be >= 1, got {self.batch_windows}")
        need(0.0 <= self.gamma < 1.0, f"gamma must be in [0, 1), got {self.gamma}")
        need(0.0 < self.tau <= 1.0, f"tau must be in (0, 1], got {self.tau}")
        for name in ("lr_critic", "lr_actor", "reward_scale"):
            v = getattr(self, name)
            need(v > 0 and math.isfinite(v), f"{name} must be > 0, got {v}")
        need(self.grad_clip >= 0, f"grad_clip must be >= 0, got {self.grad_clip}")
        need(self.action_gradient in ACTION_GRADIENTS,
             f"action_gradient must be one of {', '.join(ACTION_GRADIENTS)}, got '{self.action_gradient}'")
        need(self.warmup_episodes >= 0 and self.episodes >= 0, "warmup_episodes and episodes must be >= 0")
        need(self.updates_per_step >= 0, f"updates_per_step must be >= 0, got {self.updates_per_step}")
        need(self.noise_theta >= 0 and self.noise_sigma >= 0, "noise_theta and noise_sigma must be >= 0")
        need(1 <= self.n_envs <= 4096, f"n_envs must be in 1..4096, got {self.n_envs}")
        need(1 <= self.threads <= 256, f"threads must be in 1..256, got {self.threads}")
        need(self.eval_every >= 1 and self.eval_episodes >= 1, "eval_every and eval_episodes must be >= 1")
        need(self.checkpoint_every >= 0, f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        need(self.max_minutes >= 0, f"max_minutes must be >= 0, got {self.max_minutes}")
        need(0 <= self.seed < 2 ** 63, f"seed must be a non-negative integer, got {self.seed}")
        need(self.demo_policy in DEMO_POLICIES, f"demo_policy must be one of {', '.join(DEMO_POLICIES)}, got '{self.demo_policy}'")
        need(self.demo_episodes >= 1 and self.bc_updates >= 0 and self.demo_windows >= 0,
             "demo_episodes must be >= 1, bc_updates and demo_windows >= 0")
        need(self.actor_delay >= 0 and self.critic_pretrain >= 0,
             f"actor_delay and critic_pretrain must be >= 0, got {self.actor_delay}, {self.critic_pretrain}")
        need(self.bc_lr > 0 and math.isfinite(self.bc_lr), f"bc_lr must be > 0, got {self.bc_lr}")
        need(self.bc_weight >= 0 and math.isfinite(self.bc_weight), f"bc_weight must be >= 0, got {self.bc_weight}")
        need(re.fullmatch(r"[A-Za-z0-9._-]+", self.exp_name) is not None,
             f"exp_name may hold letters, digits, '-', '_' and '.', got '{self.exp_name}'")
        T = self.world_config().episode_steps
        need(self.unroll <= T, f"unroll ({self.unroll}) must be <= episode_steps ({T})")
        need(self.replay_size >= T * self.n_envs,
             f"replay_size ({self.replay_size}) must hold one episode per env ({T} x {self.n_envs})")
        return self

    def world_config(self):
        """The world this run trains in."""
        if self.episode_steps:
            return world_preset(self.world, episode_steps=self.episode_steps)
        return world_preset(self.world)

    @property
    def total_episodes(self) -> int:
        return self.warmup_episodes + self.episodes

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["critic_hidden"] = list(self.critic_hidden)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any], base: "RecurrentConfig | None" = None) -> "RecurrentConfig":
        """Fields of ``d`` replace those of ``base`` (default: the defaults); unknown keys are an error."""
        if not isinstance(d, dict):
            raise ConfigError(f"a training config must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - set(_HINTS))
        if unknown:
            raise ConfigError(f"unknown recurrent training field(s): {', '.join(unknown)}")
        return dataclasses.replace(base or cls(), **{k: _coerce(k, v) for k, v in d.items()})


_HINTS = typing.get_type_hints(RecurrentConfig)

#: presets (``--preset``): fields that differ from the defaults
PRESETS: dict[str, dict[str, Any]] = {
    "fast": {},
    "quick": {"max_minutes": 5.0, "replay_size": 100_000, "eval_every": 12_800, "exp_name": "gru-quick"},
    # demonstrations + behaviour cloning, then a long critic-only phase and small, BC-anchored actor steps
    # through clip (not inverting) gradients: the clone's commands sit at 0 and 1, where inverting
    # gradients can only push them inwards (README: guided MAGRDPG)
    "guided": {"demo_policy": "searcher", "bc_weight": 1000.0, "actor_delay": 20_000, "lr_actor": 3e-5,
               "noise_sigma": 0.1, "action_gradient": "clip", "exp_name": "gru-guided"},
}


def _coerce(name: str, value: Any) -> Any:
    """A JSON / CLI value as the field's type; one-line error naming the field."""
    hint = _HINTS[name]
    try:
        if hint is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(value)
            return int(value)
        if hint is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if hint is str:
            if not isinstance(value, str):
                raise ValueError(value)
            return value
        if typing.get_origin(hint) is tuple:
            vals = [value] if isinstance(value, (int, str)) else list(value)
            return tuple(_coerce_int(v) for v in vals)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: cannot read {value!r} as {getattr(hint, '__name__', hint)}") from None
    raise ConfigError(f"{name}: unsupported field type {hint}")  # pragma: no cover


def _coerce_int(v: Any) -> int:
    if isinstance(v, bool) or (isinstance(v, float) and not v.is_integer()):
        raise ValueError(v)
    return int(v)


# --------------------------------------------------------------------------------------------
# Windows of stored episodes
# --------------------------------------------------------------------------------------------
@dataclass
class Windows:
    """A minibatch of N windows (NumPy): L = burn_in + unroll + 1 inputs, unroll transitions.

    A window starts at tuple k_0 = max(0, t_s - burn_in) with a zero hidden state (exact when
    k_0 = 0: the episode's own start), so step t_s is at position ``off = t_s - k_0``; positions
    beyond the episode's stored end repeat its last tuple and are never used.
    """

    x: np.ndarray  #: (N, L, M, D) actor inputs [a_{k-1}, o_k] for k = k_0 .. k_0 + L - 1
    off: np.ndarray  #: (N,) position of t_s in the window (burn-in steps actually replayed)
    s: np.ndarray  #: (N, U, S) s_t for t = t_s .. t_s + U - 1
    a: np.ndarray  #: (N, U, M, 2) executed actions a_t
    r: np.ndarray  #: (N, U) rewards r_t
    s2: np.ndarray  #: (N, U, S) s_{t+1}


def concat_windows(a: Windows, b: Windows) -> Windows:
    """The windows of ``a`` followed by those of ``b`` (same burn-in and unroll)."""
    return Windows(**{f.name: np.concatenate([getattr(a, f.name), getattr(b, f.name)]) for f in dataclasses.fields(Windows)})


def sample_windows(replay: EpisodeReplay, n: int, burn_in: int, unroll: int, rng: np.random.Generator) -> Windows:
    """N windows with start t_s uniform over every stored (episode, t_s <= filled - unroll)."""
    starts = np.maximum(replay.filled - unroll + 1, 0)  # (C,) admissible t_s per slot
    cum = np.cumsum(starts)
    total = int(cum[-1])
    assert total > 0, f"no stored episode holds {unroll} transitions yet"
    k = rng.integers(0, total, n)
    e = np.searchsorted(cum, k, side="right")  # (N,) slot
    ts = k - (cum[e] - starts[e])  # (N,) t_s in 0 .. filled - unroll
    k0 = np.maximum(ts - burn_in, 0)
    idx = np.minimum(k0[:, None] + np.arange(burn_in + unroll + 1), replay.filled[e][:, None])  # (N, L)
    t = ts[:, None] + np.arange(unroll)  # (N, U)
    ec = e[:, None]
    return Windows(x=replay.tuples[ec, idx], off=ts - k0, s=replay.states[ec, t],
                   a=replay.tuples[ec, t + 1, :, :ACTION_DIM], r=replay.rewards[ec, t], s2=replay.states[ec, t + 1])


# --------------------------------------------------------------------------------------------
# The algorithm
# --------------------------------------------------------------------------------------------
class MAGRDPG:
    """Recurrent actor, centralised critic, their targets, optimisers and the update of Algorithm 5."""

    def __init__(self, in_dim: int, state_dim: int, n_robots: int, hidden: int, critic_hidden: tuple[int, ...],
                 gamma: float, tau: float, lr_actor: float, lr_critic: float, reward_scale: float = 1.0,
                 burn_in: int = 8, grad_clip: float = 0.0, action_gradient: str = "invert", cell: str = "gru") -> None:
        assert action_gradient in ACTION_GRADIENTS, f"unknown action_gradient {action_gradient!r}"
        self.n_robots, self.burn_in, self.action_gradient = n_robots, int(burn_in), action_gradient
        self.gamma, self.tau, self.reward_scale, self.grad_clip = float(gamma), float(tau), float(reward_scale), float(grad_clip)
        self.actor = RECURRENT_ACTORS[cell](in_dim, hidden)
        self.critic = Critic(state_dim, n_robots, critic_hidden)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for p in list(self.actor_target.parameters()) + list(self.critic_target.parameters()):
            p.requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr_actor, fused=True)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=lr_critic, fused=True)

    @torch.no_grad()
    def act(self, x: np.ndarray, h: torch.Tensor) -> tuple[np.ndarray, torch.Tensor]:
        """Raw (linear) actions for inputs x (R, D) and states h (R, H): (float64 (R, 2), new states)."""
        a, h = self.actor.step(torch.as_tensor(x, dtype=torch.float32), h)
        return a.double().numpy(), h

    def update(self, w: Windows, n_demo: int = 0, bc_weight: float = 0.0, train_actor: bool = True) -> UpdateStats:
        """One critic step on every window transition, one BPTT actor step (eq. 3.2), soft updates.

        The last ``n_demo`` windows are demonstrations: on their steps the actor also descends
        ``bc_weight`` x the squared error to the demonstrated commands, where the critic rates the
        demonstrated joint action above the actor's (Q-filter). ``train_actor=False``: the critic
        step and its soft update only.
        """
        N, L, M, D = w.x.shape
        U, B = w.s.shape[1], self.burn_in
        assert L == B + U + 1, f"window of {L} inputs does not match burn_in {B} + unroll {U} + 1"
        X = torch.from_numpy(np.ascontiguousarray(w.x.transpose(0, 2, 1, 3)).reshape(N * M, L, D))  # rows n*M + m
        off = torch.from_numpy(np.repeat(w.off, M))  # (N*M,) position of t_s
        pos = off[:, None] + torch.arange(U)  # (N*M, U) positions of t_s .. t_s + U - 1
        rows = torch.arange(N * M)[:, None]
        s = torch.from_numpy(w.s.reshape(N * U, -1))
        a = torch.from_numpy(w.a.reshape(N * U, M, ACTION_DIM))
        r = torch.from_numpy(w.r.reshape(N * U))
        s2 = torch.from_numpy(w.s2.reshape(N * U, -1))
        h0 = self.actor.initial_state(N * M)

        def per_step(y: torch.Tensor) -> torch.Tensor:  # (N*M, U, 2) -> (N*U, M, 2), rows n*U + t
            return y.reshape(N, M, U, ACTION_DIM).permute(0, 2, 1, 3).reshape(N * U, M, ACTION_DIM)

        # critic: y_t = r_t + γ Q'(s_{t+1}, μ'(x_{t+1}, h'_t)) for every step of the window
        with torch.no_grad():
            a2_all, _ = self.actor_target(X, h0)  # (N*M, L, 2)
            a2 = per_step(a2_all[rows, pos + 1]).clamp(A_MIN, A_MAX)
            y = self.reward_scale * r + self.gamma * self.critic_target(s2, a2)
        q = self.critic(s, a)
        critic_loss = torch.mean((q - y) ** 2)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()

        if not train_actor:
            soft_update(self.critic_target, self.critic, self.tau)
            return UpdateStats(critic_loss=float(critic_loss.detach()), q_mean=float(q.detach().mean()))

        # actor: burn-in (positions < off) without gradient, then BPTT over the unroll
        a_raw, _ = self.actor(X[rows, pos], self.burn_in_state(X, off))  # (N*M, U, 2)
        a_pol = per_step(a_raw)
        a_in = a_pol.detach().requires_grad_(True)
        if self.action_gradient == "clip":  # ∇ of Q(s, clip(a)): zero for components beyond a bound
            q_pol = self.critic(s, a_in.clamp(A_MIN, A_MAX))
            (g,) = torch.autograd.grad(q_pol.sum(), a_in)
        else:
            q_pol = self.critic(s, a_in)
            (dq_da,) = torch.autograd.grad(q_pol.sum(), a_in)
            g = invert_gradients(dq_da, a_in.detach())
        self.actor_opt.zero_grad(set_to_none=True)
        objective = torch.sum(a_pol * (-g / (N * U)))  # its gradient ascends (1 / N U) Σ_j Σ_t Σ_i g · μ
        bc_pass = float("nan")
        if n_demo and bc_weight > 0:
            d = slice((N - n_demo) * U, N * U)  # rows of the demonstration steps
            with torch.no_grad():
                keep = (self.critic(s[d], a[d]) > q_pol.detach()[d]).to(a_pol.dtype)  # (n_demo U,) Q-filter
            err = torch.sum((a_pol[d] - a[d]) ** 2, dim=(1, 2))  # (n_demo U,) over robots and motors
            objective = objective + bc_weight * torch.sum(keep * err) / (n_demo * U * M)
            bc_pass = float(keep.mean())
        objective.backward()
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.actor.parameters(), self.grad_clip)
        self.actor_opt.step()
        soft_update(self.critic_target, self.critic, self.tau)
        soft_update(self.actor_target, self.actor, self.tau)
        return UpdateStats(critic_loss=float(critic_loss.detach()), q_mean=float(q.detach().mean()), bc_pass=bc_pass)

    @torch.no_grad()
    def burn_in_state(self, X: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
        """The online actor's state after replaying each row's first ``off`` inputs from zero (no gradient).

        X (R, L, D) windows, off (R,) in 0..burn_in -> (R, H).
        """
        h0 = self.actor.initial_state(X.shape[0])
        if self.burn_in == 0:
            return h0
        hs = self.actor.states(X[:, :self.burn_in], h0)  # (R, B, H) state after each position
        return torch.where((off > 0)[:, None], hs[torch.arange(X.shape[0]), (off - 1).clamp(min=0)], h0)

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "actor_target": self.actor_target.state_dict(), "critic_target": self.critic_target.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        for name in ("actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt"):
            getattr(self, name).load_state_dict(d[name])


def torch_swarm_policy(agent: MAGRDPG, world) -> StatefulActor:
    """The learning actor as a deterministic SwarmPolicy (evaluation)."""
    def step(x: np.ndarray, h: torch.Tensor):
        return agent.act(x, h)
    return StatefulActor(step, agent.actor.initial_state, world)


def actor_artifact(agent: MAGRDPG, cfg: RecurrentConfig, world, c: Counters, metrics: dict) -> RecurrentPolicy:
    """The current actor as a policy artifact of its cell's kind, with provenance."""
    prov = {"trainer": "kiloforge.learn MAGRDPG", "config": cfg.to_dict(), "seed": cfg.seed, "git": git_hash(),
            "torch": torch.__version__, "trained_robots": cfg.n_robots, "env_steps": c.env_steps,
            "updates": c.updates, "wall_s": round(c.wall_s, 1), "eval": finite_or_none(dict(metrics))}
    return agent.actor.policy(world, prov)


# --------------------------------------------------------------------------------------------
# The training loop
# --------------------------------------------------------------------------------------------
@dataclass
class RunResult:
    run_dir: Path
    counters: Counters
    stopped: str


def train_recurrent(cfg: RecurrentConfig, run_dir: str | os.PathLike, resume: bool = False, progress: bool = True,
                    log: Callable[[str], None] = print) -> RunResult:
    """Train MAGRDPG with ``cfg`` into ``run_dir`` (layout of :mod:`learn.train`); ``resume`` continues."""
    cfg.validate()
    run_dir = Path(run_dir)
    prepare_run_dir(run_dir, resume)
    world = cfg.world_config()
    M, B, T = cfg.n_robots, cfg.n_envs, world.episode_steps
    D, S = world.tuple_dim, world.state_dim(M)

    # same seeding scheme as learn.train: equal seeds give MAGDDPG's evaluation episodes
    torch.set_num_threads(cfg.threads)
    ss_init, ss_env, ss_noise, ss_replay, ss_eval, ss_demo = np.random.SeedSequence(cfg.seed).spawn(6)
    torch.manual_seed(int(ss_init.generate_state(1, np.uint64)[0]))
    env_rng = np.random.default_rng(ss_env)
    noise_rng = np.random.default_rng(ss_noise)
    sample_rng = np.random.default_rng(ss_replay)
    eval_seed = int(ss_eval.generate_state(1, np.uint32)[0])

    env = SwarmEnv(world, n_envs=B, n_robots=M, seed=int(env_rng.integers(2 ** 31)))
    agent = MAGRDPG(D, S, M, cfg.hidden, cfg.critic_hidden, cfg.gamma, cfg.tau, cfg.lr_actor, cfg.lr_critic,
                    cfg.reward_scale, cfg.burn_in, cfg.grad_clip, cfg.action_gradient, cfg.cell)
    replay = EpisodeReplay(cfg.replay_size, T, M, D, S, 1)
    noise = OUNoise((B, M, ACTION_DIM), cfg.noise_theta, cfg.noise_sigma, cfg.noise_mu, noise_rng)
    evaluator = Evaluator(world, M, 1, cfg.eval_episodes, eval_seed)
    demos = None
    if cfg.demo_policy != "none":  # regenerated from the seed on --resume (deterministic), not stored
        demo_rng = np.random.default_rng(ss_demo)
        demos = _collect_demos(cfg, world, demo_rng, progress, log)
    c = Counters()
    if resume:
        ck = load_checkpoint(run_dir / "checkpoint.pt")
        if ck.get("version") != CHECKPOINT_VERSION or ck.get("trainer") != "magrdpg":
            raise ConfigError(f"'{run_dir}/checkpoint.pt' is not a MAGRDPG checkpoint of version {CHECKPOINT_VERSION}")
        may_change = ("episodes", "max_minutes", "threads", "checkpoint_every")
        defaults = RecurrentConfig().to_dict()  # fields newer than the checkpoint: their defaults ran then
        diff = sorted(k for k, v in cfg.to_dict().items()
                      if k not in may_change and ck["config"].get(k, defaults[k]) != v)
        if diff:
            raise ConfigError(f"cannot resume with a different {', '.join(diff)}")
        agent.load_state_dict(ck["agent"])
        replay.load_state_dict(ck["replay"])
        env_rng.bit_generator.state = ck["rng"]["env"]
        noise_rng.bit_generator.state = ck["rng"]["noise"]
        sample_rng.bit_generator.state = ck["rng"]["replay"]
        torch.set_rng_state(ck["rng"]["torch"])
        c = Counters(**ck["counters"])
        log(f"resumed {run_dir} at {c.env_steps} transitions, {c.updates} updates")
    else:
        write_atomic(run_dir / "config.json", cfg.to_json() + "\n")
        write_atomic(run_dir / "world.json", json.dumps(world.to_dict(), indent=2, sort_keys=True) + "\n")
        if demos is not None and cfg.bc_updates:
            _pretrain(cfg, agent, world, demos, evaluator, demo_rng, run_dir, c, progress, log)
        if demos is not None and cfg.critic_pretrain:
            _pretrain_critic(cfg, agent, demos, sample_rng, progress, log)

    def snapshot() -> dict:
        return {"version": CHECKPOINT_VERSION, "trainer": "magrdpg", "config": cfg.to_dict(),
                "agent": agent.state_dict(), "replay": replay.state_dict(),
                "rng": {"env": env_rng.bit_generator.state, "noise": noise_rng.bit_generator.state,
                        "replay": sample_rng.bit_generator.state, "torch": torch.get_rng_state()},
                "counters": vars(c)}

    def export(name: str, metrics: dict) -> None:
        save_policy(actor_artifact(agent, cfg, world, c, metrics), run_dir / name)

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.total_episodes * T, initial=min(c.env_steps, cfg.total_episodes * T), unit="step",
                   dynamic_ncols=True, desc=run_dir.name[:40], smoothing=0.05)
    session_start = time.perf_counter()
    wall_at_start = c.wall_s
    stopped = "done"
    train_returns: list[float] = []
    losses: list[tuple[float, float]] = []
    try:
        while c.episodes < cfg.total_episodes:
            t0 = time.perf_counter()
            obs, _ = env.reset(seed=int(env_rng.integers(2 ** 31)))
            x = np.concatenate([np.zeros((B, M, ACTION_DIM), np.float32), obs.astype(np.float32)], -1)  # (a_0 = 0, o_1)
            h = agent.actor.initial_state(B * M)
            noise.reset()
            replay.begin(x, env.state())
            learning = c.episodes >= cfg.warmup_episodes
            ep_return = np.zeros(B)
            upd_time = 0.0
            for t in range(T):
                raw, h = agent.act(x.reshape(B * M, D), h)
                a = np.clip(raw.reshape(B, M, ACTION_DIM) + noise.sample(), A_MIN, A_MAX).astype(np.float32)
                obs, reward, _, truncated, _ = env.step(a)
                x = np.concatenate([a, obs.astype(np.float32)], -1)  # (B, M, D)
                replay.add(x, env.state(), reward)
                ep_return += reward
                c.env_steps += B
                if learning:
                    c.update_debt += B * cfg.updates_per_step
                    u0 = time.perf_counter()
                    while c.update_debt >= 1.0:
                        w = sample_windows(replay, cfg.batch_windows, cfg.burn_in, cfg.unroll, sample_rng)
                        n_demo = cfg.demo_windows if demos is not None else 0
                        if n_demo:
                            w = concat_windows(w, sample_windows(demos, n_demo, cfg.burn_in, cfg.unroll, sample_rng))
                        st = agent.update(w, n_demo, cfg.bc_weight, train_actor=c.updates >= cfg.actor_delay)
                        losses.append((st.critic_loss, st.q_mean, st.bc_pass))
                        c.update_debt -= 1.0
                        c.updates += 1
                    upd_time += time.perf_counter() - u0
                if bar is not None:
                    bar.update(B)
            assert np.all(truncated), "the env did not truncate after episode_steps steps"
            c.episodes += B
            train_returns.extend(ep_return.tolist())
            elapsed = time.perf_counter() - t0
            c.update_s += upd_time
            c.env_s += elapsed - upd_time
            c.wall_s = wall_at_start + (time.perf_counter() - session_start)

            over_time = cfg.max_minutes > 0 and (time.perf_counter() - session_start) >= 60 * cfg.max_minutes
            last = c.episodes >= cfg.total_episodes or over_time
            if c.env_steps >= c.next_eval or last:
                _evaluate_and_log(cfg, agent, world, evaluator, c, train_returns, losses, run_dir, export, log, bar)
                train_returns, losses = [], []
                while c.next_eval <= c.env_steps:
                    c.next_eval += cfg.eval_every
                if last or (cfg.checkpoint_every and c.evals % cfg.checkpoint_every == 0):
                    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
                    save_checkpoint(snapshot(), run_dir / "checkpoint.pt")
            if over_time:
                stopped = "time"
                break
    except KeyboardInterrupt:
        stopped = "interrupted"
        log("interrupted: policy_last.npz holds the current actor; --resume continues from the last checkpoint")
        export("policy_last.npz", c.rows[-1] if c.rows else {})
    finally:
        if bar is not None:
            bar.close()
    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
    write_summary(run_dir, cfg, c, stopped)
    return RunResult(run_dir, c, stopped)


def _phase_bar(progress: bool, total: int, unit: str, desc: str):
    """A transient tqdm bar for one preparation phase (a silent no-op bar without ``progress``)."""
    from tqdm import tqdm
    return tqdm(total=total, unit=unit, desc=desc, dynamic_ncols=True, leave=False, disable=not progress)


def _collect_demos(cfg: RecurrentConfig, world, rng: np.random.Generator, progress: bool, log) -> EpisodeReplay:
    """The demonstrator's episodes (learn.demos), with a progress bar."""
    t0 = time.perf_counter()
    with _phase_bar(progress, cfg.demo_episodes, "episode", "demonstrations") as bar:
        demos = collect_demos(world, cfg.n_robots, cfg.demo_episodes, cfg.n_envs, rng, bar.update)
    log(f"demonstrations: {int((demos.filled > 0).sum())} episodes of the {cfg.demo_policy} "
        f"in {time.perf_counter() - t0:.0f} s")
    return demos


def _pretrain(cfg: RecurrentConfig, agent: MAGRDPG, world, demos: EpisodeReplay, evaluator, rng, run_dir: Path,
              c: Counters, progress: bool, log) -> None:
    """Behaviour cloning of the actor (and its target) on the demonstrations; evaluate and keep that actor."""
    t0 = time.perf_counter()
    with _phase_bar(progress, cfg.bc_updates, "update", "behaviour cloning") as bar:
        loss = bc_pretrain(agent.actor, demos, cfg.bc_updates, cfg.batch_windows, cfg.bc_lr, rng,
                           lambda k, l: bar.update(1))
    agent.actor_target.load_state_dict(agent.actor.state_dict())
    bc_s = time.perf_counter() - t0
    demo_m = rollout(evaluator.env, demonstrator(world), evaluator.episodes, seed=evaluator.seed).metrics()
    bc_m = rollout(evaluator.env, torch_swarm_policy(agent, world), evaluator.episodes, seed=evaluator.seed).metrics()
    info = {"demo_policy": cfg.demo_policy, "demo_episodes": int((demos.filled > 0).sum()),
            "bc_updates": cfg.bc_updates, "bc_loss": loss, "bc_s": round(bc_s, 1),
            "eval_demonstrator": finite_or_none(metrics_row(demo_m)), "eval_after_bc": finite_or_none(metrics_row(bc_m))}
    write_atomic(run_dir / "demos.json", json.dumps(info, indent=2, sort_keys=True) + "\n")
    clone = actor_artifact(agent, cfg, world, c, metrics_row(bc_m))
    save_policy(clone, run_dir / "policy_bc.npz")
    save_policy(clone, run_dir / "policy_best.npz")
    c.best_return = info["eval_after_bc"]["eval_return"]  # RL must beat the cloned actor to replace it as best
    log(f"behaviour cloning: loss {loss:.4f} in {bc_s:.0f} s; evaluation return {info['eval_after_bc']['eval_return']:.1f}, "
        f"final coverage {info['eval_after_bc']['eval_final_coverage']:.3f} "
        f"(demonstrator {info['eval_demonstrator']['eval_final_coverage']:.3f})")


def _pretrain_critic(cfg: RecurrentConfig, agent: MAGRDPG, demos: EpisodeReplay, rng: np.random.Generator,
                     progress: bool, log) -> None:
    """Critic-only updates on demonstration windows: Q of the (cloned) actor before the actor may move."""
    t0 = time.perf_counter()
    qs = []
    with _phase_bar(progress, cfg.critic_pretrain, "update", "critic on demonstrations") as bar:
        for _ in range(cfg.critic_pretrain):
            w = sample_windows(demos, cfg.batch_windows + cfg.demo_windows, cfg.burn_in, cfg.unroll, rng)
            qs.append(agent.update(w, train_actor=False).q_mean)
            bar.update(1)
    log(f"critic pre-training: {cfg.critic_pretrain} updates on demonstrations in {time.perf_counter() - t0:.0f} s, "
        f"mean Q {np.mean(qs[-100:]):.1f}")


def _mean_finite(xs: list[float]) -> float:
    """Mean of the finite values (NaN when there are none)."""
    v = [x for x in xs if math.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def _evaluate_and_log(cfg, agent, world, evaluator, c, train_returns, losses, run_dir, export, log, bar) -> None:
    """Evaluate deterministically (MAGDDPG's episodes), append a metrics row, export, redraw the curve."""
    from .plots import plot_learning_curves

    m = rollout(evaluator.env, torch_swarm_policy(agent, world), evaluator.episodes, seed=evaluator.seed).metrics()
    row = {"env_steps": c.env_steps, "episodes": c.episodes, "updates": c.updates, "wall_s": round(c.wall_s, 2),
           **metrics_row(m),
           "train_return": float(np.mean(train_returns)) if train_returns else float("nan"),
           "critic_loss": float(np.mean([x[0] for x in losses])) if losses else float("nan"),
           "q_mean": float(np.mean([x[1] for x in losses])) if losses else float("nan"),
           "bc_pass": _mean_finite([x[2] for x in losses]),  # NaN while the actor waits or without demos
           "env_steps_per_s": c.env_steps / c.env_s if c.env_s > 0 else float("nan"),
           "updates_per_s": c.updates / c.update_s if c.update_s > 0 else float("nan")}
    c.rows.append(row)
    c.evals += 1
    export("policy_last.npz", row)
    if row["eval_return"] > c.best_return:
        c.best_return = row["eval_return"]
        export("policy_best.npz", row)
    write_atomic(run_dir / "metrics.csv", rows_to_csv(c.rows))
    plot_learning_curves({run_dir.name: c.rows}, run_dir / "learning_curve.png",
                         title=f"MAGRDPG, {cfg.n_robots} robots, {cfg.cell.upper()} {cfg.hidden} ({cfg.world} world)")
    msg = (f"return {row['eval_return']:.1f}  final cov {row['eval_final_coverage']:.2f}  "
           f"find {row['eval_time_to_find']:.0f}")
    if bar is not None:
        bar.set_postfix_str(f"{msg}  upd/s {row['updates_per_s']:.0f}", refresh=True)
    else:
        log(f"[{c.env_steps} steps, {c.updates} updates, {c.wall_s:.0f} s] {msg}")


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit status 2)."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _field_docs() -> dict[str, str]:
    docs = {}
    for line in inspect.getsource(RecurrentConfig).splitlines():
        m = re.match(r"\s+(\w+): .*?#: (.*)$", line)
        if m:
            docs[m.group(1)] = m.group(2).strip()
    return docs


def build_parser(prog: str = "python -m learn train-recurrent") -> argparse.ArgumentParser:
    """Options: --preset, --config, --out, --resume, --quiet and one per RecurrentConfig field."""
    p = _Parser(prog=prog, description="Train a recurrent (GRU or LSTM) swarm policy with MAGRDPG (thesis Algorithm 5).")
    p.add_argument("--preset", default=None, choices=list(PRESETS), help="training preset (default 'fast')")
    p.add_argument("--config", default=None, help="JSON file of RecurrentConfig fields")
    p.add_argument("--out", default=None, help="run directory (default runs/<task>__<exp>__<seed>__<time>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar; one line per evaluation")
    docs = _field_docs()
    g = p.add_argument_group("training configuration (RecurrentConfig fields)")
    for f in dataclasses.fields(RecurrentConfig):
        flags = (["--robots"] if f.name == "n_robots" else []) + [f"--{f.name.replace('_', '-')}"]
        kw: dict = {"dest": f.name, "default": argparse.SUPPRESS, "type": str}
        if typing.get_origin(_HINTS[f.name]) is tuple:
            kw.update(nargs="+", metavar="N", help=f"{docs.get(f.name, '')} (default {' '.join(map(str, f.default))})")
        else:
            kw.update(metavar=_HINTS[f.name].__name__.upper(), help=f"{docs.get(f.name, '')} (default {f.default})")
        g.add_argument(*flags, **kw)
    return p


def resolve_config(args: argparse.Namespace) -> tuple[RecurrentConfig, Path]:
    """defaults < --preset < --config < options; --resume reads the run's config.json."""
    given = {f: _coerce(f, getattr(args, f)) for f in _HINTS if hasattr(args, f)}
    if args.resume:
        if not args.out:
            raise ConfigError("--resume needs --out RUN_DIR")
        cfg = RecurrentConfig.from_dict(_read_json(Path(args.out) / "config.json"))
        return dataclasses.replace(cfg, **given).validate(), Path(args.out)
    cfg = RecurrentConfig.from_dict(PRESETS[args.preset or "fast"])
    if args.config:
        cfg = RecurrentConfig.from_dict(_read_json(Path(args.config)), base=cfg)
    cfg = dataclasses.replace(cfg, **given).validate()
    out = Path(args.out) if args.out else Path("runs") / f"{TASK}__{cfg.exp_name}__{cfg.seed}__{int(time.time())}"
    return cfg, out


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"'{path}' does not exist") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ConfigError(f"cannot read '{path}': {e}") from None


def main_train_recurrent(argv: list[str] | None = None, prog: str = "python -m learn train-recurrent") -> int:
    """CLI entry point; returns the exit status (2 with a one-line message for user errors)."""
    from export.codegen.budget import estimate
    from kiloforge.actors.base import HiddenArch
    from kiloforge.actors.registry import kind_named
    from kiloforge.errors import KiloforgeError

    args = build_parser(prog).parse_args(sys.argv[1:] if argv is None else list(argv))
    try:
        cfg, out = resolve_config(args)
        budget = estimate(kind_named(cfg.cell), cfg.world_config(), HiddenArch(cfg.hidden))
        if not budget.ok:
            print(f"note: an actor of {cfg.hidden} {cfg.cell.upper()} units does not fit the Kilobot budget ({budget.summary()}); "
                  "it trains, but the exporter will refuse it", file=sys.stderr)
        res = train_recurrent(cfg, out, resume=args.resume, progress=not args.quiet)
    except (ConfigError, KiloforgeError, ValueError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    c = res.counters
    best = max(c.rows, key=lambda r: r["eval_return"]) if c.rows else None
    print(f"run: {res.run_dir}  ({res.stopped})")
    print(f"  {c.env_steps} transitions, {c.updates} updates in {c.wall_s:.0f} s")
    if best:
        print(f"  best evaluation at {best['env_steps']:.0f} transitions: return {best['eval_return']:.1f}, "
              f"final coverage {best['eval_final_coverage']:.3f}, time to find {best['eval_time_to_find']:.1f}")
    pols = [str(res.run_dir / n) for n in ("policy_best.npz", "policy_last.npz", "policy_bc.npz")
            if (res.run_dir / n).is_file()]
    print(f"  policies: {', '.join(pols) if pols else 'none (no evaluation ran)'}")
    return 0


if __name__ == "__main__":
    sys.exit(main_train_recurrent(prog="python -m learn.magrdpg"))
