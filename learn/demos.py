"""Demonstrations for guided learning: episodes of a scripted policy, and behaviour cloning on them.

MAGRDPG can start from a *demonstrator* instead of from scratch (``--demo-policy searcher``):

1. :func:`collect_demos` runs the demonstrator in the training world and stores its episodes in an
   :class:`~learn.replay.EpisodeReplay` of their own, in the same tuple layout as the learner's
   (``x_t = [a_{t-1}, o_t]``), with states and rewards, so the critic can learn from them too;
2. :func:`bc_pretrain` fits the recurrent actor to the demonstrator's commands (mean squared error over
   whole episodes from a zero hidden state: behaviour cloning);
3. during reinforcement learning the demonstrations stay in every minibatch, and a Q-filtered
   behaviour-cloning term keeps the actor near them only where the critic rates the demonstrated
   action above the actor's own (Nair et al. 2018, "Overcoming exploration in RL with demonstrations").

The demonstrator is the hand-written searcher of :mod:`sim.baselines` with one change: it always
turns left (``turn_sign=+1``). A deterministic actor cannot imitate "left or right at random" (the
mean of the two is "straight on"); with a fixed turn direction the searcher is as good (thesis world:
0.96 vs 0.97 final coverage with 2 robots) and a GRU can copy it.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
import torch

from sim.baselines import TUNED, HandWrittenSearcher, SearcherParams
from sim.config import ACTION_DIM, WorldConfig
from sim.env import SwarmEnv

from .recurrent import GRUActor
from .replay import EpisodeReplay

DEMO_POLICIES = ("none", "searcher")  #: values of ``--demo-policy``


def demonstrator(world: WorldConfig) -> HandWrittenSearcher:
    """The hand-written searcher, tuned for ``world``, turning always left (imitable by a deterministic actor)."""
    base = TUNED.get(world.name, SearcherParams())
    return HandWrittenSearcher(world, dataclasses.replace(base, turn_sign=1))


def collect_demos(world: WorldConfig, n_robots: int, episodes: int, n_envs: int, rng: np.random.Generator,
                  progress: Callable[[int], None] | None = None) -> EpisodeReplay:
    """``episodes`` demonstrator episodes (rounded up to whole batches of ``n_envs``) in a replay of their own."""
    assert episodes >= 1 and n_envs >= 1, f"need episodes >= 1 and n_envs >= 1, got {episodes}, {n_envs}"
    T, M = world.episode_steps, n_robots
    batches = math.ceil(episodes / n_envs)
    replay = EpisodeReplay(batches * n_envs * T, T, M, world.tuple_dim, world.state_dim(M), 1)
    env = SwarmEnv(world, n_envs=n_envs, n_robots=M, seed=int(rng.integers(2 ** 31)))
    policy = demonstrator(world)
    for _ in range(batches):
        obs, _ = env.reset(seed=int(rng.integers(2 ** 31)))
        policy.reset(n_envs, M, np.random.default_rng(rng.integers(2 ** 63)))
        replay.begin(np.concatenate([np.zeros((n_envs, M, ACTION_DIM), np.float32), obs.astype(np.float32)], -1),
                     env.state())
        for _ in range(T):
            a = policy.act(obs).astype(np.float32)  # (B, M, 2) in {0, speed, 1}
            obs, reward, _, truncated, _ = env.step(a)
            replay.add(np.concatenate([a, obs.astype(np.float32)], -1), env.state(), reward)
        assert np.all(truncated), "the env did not truncate after episode_steps steps"
        if progress is not None:
            progress(n_envs)
    return replay


def episode_sequences(replay: EpisodeReplay) -> tuple[torch.Tensor, torch.Tensor]:
    """Every stored episode as per-robot sequences: inputs (E·M, T, D) and the commands taken (E·M, T, 2)."""
    full = np.flatnonzero(replay.filled == replay.T)
    assert full.size, "no complete demonstration episode stored"
    x = replay.tuples[full]  # (E, T + 1, M, D)
    E, L, M, D = x.shape
    seq = np.ascontiguousarray(x.transpose(0, 2, 1, 3))  # (E, M, T + 1, D)
    inputs = seq[:, :, :-1].reshape(E * M, L - 1, D)  # x_0 .. x_{T-1}
    targets = seq[:, :, 1:, :ACTION_DIM].reshape(E * M, L - 1, ACTION_DIM)  # a_t is stored in x_{t+1}
    return torch.from_numpy(inputs), torch.from_numpy(targets)


def bc_pretrain(actor: GRUActor, replay: EpisodeReplay, updates: int, batch: int, lr: float,
                rng: np.random.Generator, progress: Callable[[int, float], None] | None = None) -> float:
    """Behaviour cloning: ``updates`` Adam steps of mean squared error on whole demonstration episodes.

    Each step takes ``batch`` robot-episodes at random and unrolls the actor over all T steps from a
    zero hidden state, exactly as it will run. Returns the mean loss of the last 10 % of the steps.
    """
    X, A = episode_sequences(replay)
    opt = torch.optim.Adam(actor.parameters(), lr=lr)
    tail: list[float] = []
    for k in range(updates):
        idx = torch.from_numpy(rng.integers(0, X.shape[0], batch))
        y, _ = actor(X[idx], actor.initial_state(batch))
        loss = torch.mean((y - A[idx]) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if k >= updates - max(1, updates // 10):
            tail.append(float(loss.detach()))
        if progress is not None:
            progress(k, float(loss.detach()))
    return float(np.mean(tail)) if tail else float("nan")
