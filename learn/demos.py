"""Demonstrations for guided learning: episodes of a scripted policy, and behaviour cloning on them.

Any actor (MLP or recurrent) can start from a *demonstrator* instead of from scratch
(``--demo-policy searcher``):

1. :func:`collect_demos` runs the demonstrator in the training world and stores its episodes in an
   :class:`~learn.replay.EpisodeReplay` of their own, in the learner's tuple layout
   (``x_t = [a_{t-1}, o_t]``), with states and rewards, so the critic can learn from them too;
2. :func:`bc_pretrain` fits the actor to the demonstrator's commands through the exact input pipeline
   of the firmware (mean squared error): the MLP on the T_prev histories the robot would hold
   (Algorithm 4's first-tuple fill included), the recurrent actor unrolled over whole episodes from
   the zero state (the algorithms' ``bc_loss``);
3. during reinforcement learning demonstration samples stay in every minibatch, and a Q-filtered
   behaviour-cloning term keeps the actor near them only where the critic rates the demonstrated
   action above the actor's own (Nair et al. 2018; :class:`learn.ddpg.CentralisedDDPG`).

The demonstrator is the hand-written searcher of :mod:`sim.baselines` with one change: it always
turns left (``turn_sign=+1``). A deterministic actor cannot imitate "left or right at random" (the
mean of the two is "straight on"); with a fixed turn direction the searcher is as good (thesis world:
0.96 vs 0.97 final success with 2 robots) and an actor can copy it. ``--demo-policy pusher`` clones
the crowd variant (:data:`sim.baselines.PUSHER`) instead, turning left except at the target, where its
turns alternate (``turn_sign=2``; on held-out episodes at 32 robots 0.550, always left 0.548, turning at random
0.566), which an actor can still read off the last turn in its history.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch

from sim.baselines import PUSHER, HandWrittenSearcher, make_policy
from sim.config import ACTION_DIM, WorldConfig
from sim.env import SwarmEnv
from sim.rollout import EpisodeLoop

from .replay import EpisodeReplay


#: the demonstrators (``--demo-policy``): what each changes in the searcher's tuned parameters. "searcher" always
#: turns left; "pusher" is :data:`sim.baselines.PUSHER` turning left, except at the target, where its turns
#: alternate (deterministic, and imitable from a history that holds the last turn)
DEMONSTRATORS: dict[str, dict] = {"searcher": {"turn_sign": 1}, "pusher": {**PUSHER, "turn_sign": 2}}


def demonstrator(world: WorldConfig, stop_dist: float = 0.0, kind: str = "searcher") -> HandWrittenSearcher:
    """The demonstrator ``kind`` (a :data:`DEMONSTRATORS` key) on the searcher tuned for ``world``; ``stop_dist``
    > 0 replaces its stopping distance (fraction of the range)."""
    changes = {**DEMONSTRATORS[kind], **({"stop_dist": stop_dist} if stop_dist else {})}
    return make_policy("baseline", world, **changes)


def collect_demos(world: WorldConfig, n_robots: int, episodes: int, n_envs: int, rng: np.random.Generator,
                  progress: Callable[[int], None] | None = None, t_prev: int = 1, device: str = "cpu",
                  with_obs: bool = False, stop_dist: float = 0.0, kind: str = "searcher") -> EpisodeReplay:
    """``episodes`` demonstrator episodes (rounded up to whole batches of ``n_envs``) in a replay of their own."""
    assert episodes >= 1 and n_envs >= 1, f"need episodes >= 1 and n_envs >= 1, got {episodes}, {n_envs}"
    T, M = world.episode_steps, n_robots
    batches = math.ceil(episodes / n_envs)
    replay = EpisodeReplay(batches * n_envs * T, T, M, world.tuple_dim, world.state_dim(M), t_prev, device, with_obs)
    env = SwarmEnv(world, n_envs=n_envs, n_robots=M, seed=int(rng.integers(2 ** 31)))
    policy = demonstrator(world, stop_dist, kind)

    def begin(k: int, obs: np.ndarray, info) -> None:
        policy.reset(n_envs, M, np.random.default_rng(rng.integers(2 ** 63)))
        replay.begin(np.concatenate([np.zeros((n_envs, M, ACTION_DIM), np.float32), obs.astype(np.float32)], -1),
                     env.state())

    def act(t: int, obs: np.ndarray, info) -> np.ndarray:
        return policy.act(obs).astype(np.float32)  # (B, M, 2) in {0, speed, 1}

    def observe(t: int, a: np.ndarray, obs: np.ndarray, reward: np.ndarray, info) -> None:
        replay.add(np.concatenate([a, obs.astype(np.float32)], -1), env.state(), reward)

    end = None if progress is None else lambda k: progress(n_envs)
    env_seeds = (int(rng.integers(2 ** 31)) for _ in range(batches))  # drawn lazily: each before its batch's policy seed
    EpisodeLoop(env).run(act, env_seeds, begin, observe, end)
    return replay


def bc_pretrain(algo, demos: Sequence[EpisodeReplay], shares: Sequence[int], updates: int, lr: float,
                rng: np.random.Generator, progress: Callable[[int, float], None] | None = None) -> float:
    """Behaviour cloning: ``updates`` Adam steps of the actor on the demonstrations.

    Each step draws ``shares[g]`` samples (transitions for an MLP, robot-episodes for a recurrent
    actor) from every swarm size's demonstrations ``demos[g]`` and descends the sample-weighted mean
    of ``algo.bc_loss``. Returns the mean loss of the last 10 % of the steps. ``progress(k, loss)``
    runs after each step (it may raise to stop).
    """
    opt = torch.optim.Adam(algo.actor.parameters(), lr=lr)
    total = sum(shares)
    tail: list[float] = []
    for k in range(updates):
        loss = sum(algo.bc_loss(d, n, rng) * (n / total) for d, n in zip(demos, shares) if n)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if k >= updates - max(1, updates // 10):
            tail.append(float(loss.detach()))
        if progress is not None:
            progress(k, float(loss.detach()))
    return float(np.mean(tail)) if tail else float("nan")
