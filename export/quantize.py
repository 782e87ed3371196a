"""Post-training quantisation of a float policy of any kind into the int8 format of :mod:`kiloforge.numfmt`.

Pipeline::

    calib = calibrate(policy, episodes=1, n_robots=(4, 16), seed=0)   # simulator rollouts
    qp = quantize_policy(policy, calib)                                # the kind's QuantizedActor
    report = error_report(policy, qp, calib); print(report.table())

* :func:`calibrate` runs the float policy itself in its own world (``sim.env.SwarmEnv`` driven by the
  kind's swarm policy) and records every robot-episode's input tuples ``[a_prev, obs]``; the kind
  turns them into what its exponents must cover (an MLP's histories and layer values, a recurrent
  cell's states and gates: :meth:`~kiloforge.actors.base.ActorKind.calibration`).
* :func:`quantize_policy` and :func:`error_report` are the kind's (:mod:`kiloforge.actors`).
"""
from __future__ import annotations

import dataclasses

from typing import Any, Sequence

import numpy as np

from kiloforge.actors.base import FloatPolicy, QuantizedActor
from kiloforge.actors.registry import kind_of
from sim.config import ACTION_DIM
from sim.env import SwarmEnv
from sim.rollout import EpisodeLoop


class _TupleRecorder:
    """A swarm policy that keeps the input tuples ``[a_{t-1}, o_t]`` (R, T, D) of every robot it drives."""

    def __init__(self, actor, n_envs: int, n_robots: int, steps: int, tuple_dim: int) -> None:
        self.actor = actor
        self.prev = np.zeros((n_envs, n_robots, ACTION_DIM), np.float32)  # a_{-1} = 0
        self.xs = np.empty((n_envs * n_robots, steps, tuple_dim), np.float32)

    def begin(self, k: int, obs: np.ndarray, info) -> None:
        self.actor.reset(*obs.shape[:2])

    def act(self, t: int, obs: np.ndarray, info) -> np.ndarray:
        self.xs[:, t] = np.concatenate([self.prev, obs.astype(np.float32)], -1).reshape(self.xs.shape[0], -1)
        u = self.actor.act(obs)  # (B, M, 2) float64 in [0, 1]
        self.prev = u.astype(np.float32)
        return u


def record_sequences(policy: FloatPolicy, episodes: int = 1, n_robots: int | Sequence[int] = (4, 16), seed: int = 0,
                     steps: int | None = None, n_envs: int = 1, progress: bool = False, task: Any = None
                     ) -> tuple[np.ndarray, dict[str, Any]]:
    """Roll the float policy out in its own world on episodes of ``task`` (a :class:`sim.tasks.Task` or name;
    default localisation): (input tuples (S, T, D) float32, info).

    ``episodes`` episodes of ``steps`` control periods (default ``world.episode_steps``) for each
    robot count in ``n_robots``, ``n_envs`` parallel envs each; one row per robot-episode. The tuple
    of step t is ``[a_{t-1}, o_t]`` with ``a_{-1} = 0``, the actions as the actor returned them.
    Deterministic given ``seed``.
    """
    counts = [int(n_robots)] if np.isscalar(n_robots) else [int(m) for m in n_robots]
    assert counts and all(m >= 1 for m in counts), f"robot counts must be >= 1, got {counts}"
    assert episodes >= 1 and n_envs >= 1, "episodes and n_envs must be >= 1"
    world = policy.world
    T = int(steps if steps is not None else world.episode_steps)
    assert T >= 1, f"steps must be >= 1, got {T}"
    run_world = dataclasses.replace(world, episode_steps=T)  # episodes of T steps, longer ones too
    kind = kind_of(policy)
    seeds = np.random.SeedSequence(seed).spawn(len(counts) * episodes)
    bar = None
    if progress:
        from kiloforge.progress import progress_bar
        bar = progress_bar(total=len(counts) * episodes * T, desc="calibrating", unit="step", leave=False)
    chunks: list[np.ndarray] = []
    observe = None if bar is None else lambda *_: bar.update(1)
    try:
        for ci, m in enumerate(counts):
            for ep in range(episodes):
                env = SwarmEnv(run_world, n_envs, m, seed=int(seeds[ci * episodes + ep].generate_state(1)[0]), task=task)
                tuples = _TupleRecorder(kind.swarm_policy(policy, run_world), n_envs, m, T, world.tuple_dim)
                EpisodeLoop(env).run(tuples.act, begin=tuples.begin, observe=observe)
                chunks.append(tuples.xs)
    finally:
        if bar is not None:
            bar.close()
    info = {"episodes": episodes, "n_robots": counts, "seed": seed, "steps": T, "n_envs": n_envs, "world": world.name}
    return np.concatenate(chunks, 0), info


def calibrate(policy: FloatPolicy, episodes: int = 1, n_robots: int | Sequence[int] = (4, 16), seed: int = 0,
              steps: int | None = None, n_envs: int = 1, progress: bool = False, task: Any = None) -> Any:
    """The kind's calibration of ``policy`` over :func:`record_sequences` rollouts (episodes of ``task``)."""
    seqs, info = record_sequences(policy, episodes, n_robots, seed, steps, n_envs, progress, task)
    return kind_of(policy).calibration(policy, seqs, info)


def quantize_policy(policy: FloatPolicy, calib: Any, *, percentile: float = 100.0, headroom: float = 1.0,
                    e_in: int | None = None) -> QuantizedActor:
    """The int8 actor of ``policy`` (the kind's quantiser; raises QuantizeError)."""
    return kind_of(policy).quantize(policy, calib, percentile=percentile, headroom=headroom, e_in=e_in)


def error_report(policy: FloatPolicy, qp: QuantizedActor, calib: Any) -> Any:
    """Float vs int8 over the calibration (the kind's report: ``table()``, ``to_dict()``, ``du_max`` ...)."""
    return kind_of(policy).error_report(policy, qp, calib)
