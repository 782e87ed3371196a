"""Policies and batched rollouts: the one loop that sim, learn and export use to run a swarm.

A :class:`SwarmPolicy` maps the observations of every robot of every env, ``(B, M, obs_dim)``, to
motor commands ``(B, M, 2)`` in [0, 1]. It may keep per-robot internal state (a history, timers),
which :meth:`SwarmPolicy.reset` clears at the start of each batch of synchronised episodes.

:class:`HistoryActor` turns any function of the flat Algorithm-4 history (a trained actor, a policy
artifact's ``act``, the int8 emulator) into a :class:`SwarmPolicy`.

:func:`rollout` runs ``episodes`` episodes, ``env.n_envs`` at a time, and returns rewards, coverage
and (optionally) trajectories for plotting. Same env config, same policy, same seed ⇒ same result.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from .config import ACTION_DIM, WorldConfig
from .history import History
from .metrics import EpisodeSteps


@runtime_checkable
class SwarmPolicy(Protocol):
    """What :func:`rollout` drives: per-robot decisions for a batch of synchronised episodes."""

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        """Start new episodes for ``n_envs`` envs of ``n_robots`` robots; ``rng`` is the policy's own stream."""
        ...

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Observations (B, M, obs_dim) → actions (B, M, 2) float in [0, 1]."""
        ...


class HistoryActor:
    """A :class:`SwarmPolicy` around ``act_fn(history (..., history_dim)) -> (..., 2)``.

    Keeps the Algorithm-4 history per robot: the first observation after :meth:`reset` fills it
    with ``(a_0 = 0, o_1)`` repeated ``t_prev`` times; afterwards each call appends
    ``(previous action, obs)`` where the previous action is exactly what this actor returned last
    (after clipping to [0, 1]), as the firmware does.
    """

    def __init__(self, act_fn: Callable[[np.ndarray], np.ndarray], t_prev: int, cfg: WorldConfig) -> None:
        assert callable(act_fn), "act_fn must be callable"
        assert t_prev >= 1, f"t_prev must be >= 1, got {t_prev}"
        self.act_fn = act_fn
        self.t_prev = int(t_prev)
        self.cfg = cfg
        self.history = History(self.t_prev, cfg.obs_dim)
        self._prev_action: np.ndarray | None = None  # (B, M, 2) what act returned last; None = fresh episode

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        """Forget the history; the next :meth:`act` starts a new one (Algorithm 4)."""
        self._prev_action = None

    def act(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        assert obs.ndim == 3 and obs.shape[-1] == self.cfg.obs_dim, (
            f"HistoryActor expects obs (B, M, {self.cfg.obs_dim}), got {obs.shape}")
        if self._prev_action is None or self._prev_action.shape[:2] != obs.shape[:2]:
            flat = self.history.reset(obs)  # (B, M, t_prev * tuple_dim)
        else:
            flat = self.history.push(self._prev_action, obs)
        a = np.asarray(self.act_fn(flat), np.float64)
        assert a.shape == obs.shape[:2] + (ACTION_DIM,), (
            f"act_fn returned shape {a.shape}, expected {obs.shape[:2] + (ACTION_DIM,)}")
        a = np.clip(a, 0.0, 1.0)
        self._prev_action = a.astype(np.float32)
        return a


@dataclass
class Trajectories:
    """What a rollout recorded for rendering. E episodes, T steps, M robots."""

    positions: np.ndarray  # (E, T+1, M, 2) float32 mm, index 0 = after reset
    headings: np.ndarray  # (E, T+1, M) float32 rad
    target: np.ndarray | None  # (E, T+1, 2) float32 mm, the target beacon after each step (pushed ones move); None: no beacon
    in_range: np.ndarray  # (E, T+1, M) bool, robots counting towards success (localisation: in range; index 0 = at reset)
    actions: np.ndarray  # (E, T, M, 2) float32, the commands sent


@dataclass
class RolloutResult(EpisodeSteps):
    """Per-episode records of a :func:`rollout`."""

    cfg: WorldConfig
    n_robots: int
    seed: int | None
    rewards: np.ndarray  # (E, T) float64 team reward per step
    coverage: np.ndarray  # (E, T) float64 the task's success after each step (localisation: coverage)
    trajectories: Trajectories | None = None
    extra: dict = field(default_factory=dict)
    beacon: np.ndarray | None = None  # (E, 2) float64 mm, the target beacon at the end of each episode (None: no beacon)
    task: Any = None  #: the env's task (sim.tasks.Task): its metrics; None: localisation

    def metrics(self, ceiling: bool = False):
        """The task's metrics of these episodes (:meth:`sim.tasks.Task.episode_metrics`); ``ceiling``: also
        relative to the task's upper bound (localisation: each episode's packing ceiling)."""
        from .tasks import get_task

        return get_task(self.task).episode_metrics(self.cfg, self.n_robots, self.rewards, self.coverage, self.beacon,
                                                   ceiling)


def robot_success(info, n_envs: int, n_robots: int) -> np.ndarray:
    """(B, M) bool: the robots the task counts as successful this step (its ``robot_success`` info entry,
    all False when it has none); plots and animations highlight them."""
    flags = info.get("robot_success")
    return np.zeros((n_envs, n_robots), bool) if flags is None else flags


def rollout(env, policy: SwarmPolicy, episodes: int, seed: int | None = 0, record: bool | int = False,
            progress: bool = False) -> RolloutResult:
    """Run ``episodes`` episodes of ``policy`` in ``env``, ``env.n_envs`` synchronised at a time.

    Batch k resets the env with a seed drawn from ``SeedSequence(seed)`` stream k and hands the
    policy its own stream, so results depend only on (config, robots, n_envs, policy, seed).
    When ``episodes`` is not a multiple of ``n_envs`` the surplus envs of the last batch are dropped.
    ``record`` keeps positions, headings, the target's track, in-range flags and actions for rendering: ``True``
    for every episode, an int ``k`` for the first ``k`` episodes only (memory: long runs render one).
    ``progress`` shows a tqdm bar over all steps (on stderr).
    """
    assert episodes >= 1, f"episodes must be >= 1, got {episodes}"
    B, M, cfg = env.n_envs, env.n_robots, env.cfg
    T = cfg.episode_steps
    n_batches = math.ceil(episodes / B)
    root = np.random.SeedSequence(seed)
    batch_seqs = root.spawn(n_batches)

    n_rec = episodes if record is True else max(0, min(int(record), episodes))
    rec_batches = math.ceil(n_rec / B)  # record whole batches, trim at the end
    rewards = np.zeros((n_batches * B, T))
    coverage = np.zeros((n_batches * B, T))
    has_beacon = env.cfg.beacon
    beacon = np.zeros((n_batches * B, 2)) if has_beacon else None
    if n_rec:
        pos = np.zeros((rec_batches * B, T + 1, M, 2), np.float32)
        head = np.zeros((rec_batches * B, T + 1, M), np.float32)
        tgt = np.zeros((rec_batches * B, T + 1, 2), np.float32) if has_beacon else None
        inr = np.zeros((rec_batches * B, T + 1, M), bool)
        acts = np.zeros((rec_batches * B, T, M, 2), np.float32)

    bar = None
    if progress:
        from kiloforge.progress import progress_bar

        bar = progress_bar(total=n_batches * T, unit="step", desc=f"{episodes} episodes", leave=False)
    try:
        for k, ss in enumerate(batch_seqs):
            env_ss, pol_ss = ss.spawn(2)
            env_seed = int(env_ss.generate_state(1, np.uint32)[0])
            obs, info = env.reset(seed=env_seed)
            policy.reset(B, M, np.random.default_rng(pol_ss))
            rows = slice(k * B, (k + 1) * B)
            rec = k < rec_batches
            if rec:
                pos[rows, 0] = env.pos
                head[rows, 0] = env.heading
                if has_beacon:
                    tgt[rows, 0] = env.target
                inr[rows, 0] = robot_success(info, B, M)
            for t in range(T):
                a = np.asarray(policy.act(obs), np.float64)
                assert a.shape == (B, M, ACTION_DIM), f"policy returned {a.shape}, expected {(B, M, ACTION_DIM)}"
                obs, r, terminated, truncated, info = env.step(a)
                rewards[rows, t] = r
                coverage[rows, t] = info["success"]
                if rec:
                    pos[rows, t + 1] = env.pos
                    head[rows, t + 1] = env.heading
                    if has_beacon:
                        tgt[rows, t + 1] = env.target
                    inr[rows, t + 1] = robot_success(info, B, M)
                    acts[rows, t] = a
                if bar is not None:
                    bar.update(1)
            assert np.all(truncated), "env did not truncate after cfg.episode_steps steps"
            if has_beacon:
                beacon[rows] = env.target
    finally:
        if bar is not None:
            bar.close()

    traj = None
    if n_rec:
        traj = Trajectories(pos[:n_rec], head[:n_rec], None if tgt is None else tgt[:n_rec], inr[:n_rec], acts[:n_rec])
    return RolloutResult(cfg=cfg, n_robots=M, seed=seed, rewards=rewards[:episodes],
                         coverage=coverage[:episodes], trajectories=traj,
                         beacon=None if beacon is None else beacon[:episodes], task=env.task)
