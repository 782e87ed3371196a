"""Policies and batched rollouts: the one loop that sim, learn and export use to run a swarm.

A :class:`SwarmPolicy` maps the observations of every robot of every env, ``(B, M, obs_dim)``, to
motor commands ``(B, M, 2)`` in [0, 1]. It may keep per-robot internal state (a history, timers),
which :meth:`SwarmPolicy.reset` clears at the start of each batch of synchronised episodes.

:class:`HistoryActor` turns any function of the flat Algorithm-4 history (a trained actor, a policy
artifact's ``act``, the int8 emulator) into a :class:`SwarmPolicy`.

:class:`EpisodeLoop` is the one loop that steps an env through episodes (reset, commands from a policy
callback, step, the team reward and the task's success recorded, hooks for what else a caller keeps):
:func:`rollout`, the closed-loop verification, calibration, demonstrations, evolution strategies and the
learners' env groups all step through it, and :class:`TaskEpisodes` asks the task for the metrics.

:func:`rollout` runs ``episodes`` episodes, ``env.n_envs`` at a time, and returns rewards, the task's
success and (optionally) trajectories for plotting. Same env config, same policy, same seed ⇒ same result.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Protocol, runtime_checkable

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
    target: np.ndarray | None  # (E, T+1, 2) float32 mm, the emitter after each step (pushed ones move); None: no emitter
    in_range: np.ndarray  # (E, T+1, M) bool, robots counting towards success (localisation: in range; index 0 = at reset)
    actions: np.ndarray  # (E, T, M, 2) float32, the commands sent


class TaskEpisodes(EpisodeSteps):
    """A record of E episodes of T steps of a task: ``cfg``, ``n_robots``, team ``rewards`` and the task's
    ``success`` (E, T), ``task``, and optionally each episode's final ``emitter`` position; its metrics are the task's."""

    cfg: WorldConfig
    n_robots: int
    rewards: np.ndarray
    task: Any

    def metrics(self, ceiling: bool = False):
        """The task's metrics of these episodes (:meth:`sim.tasks.Task.episode_metrics`); ``ceiling``: also
        relative to the task's upper bound (localisation: each episode's packing ceiling)."""
        from .tasks import get_task

        return get_task(self.task).episode_metrics(self.cfg, self.n_robots, self.rewards, self.success,
                                                   getattr(self, "emitter", None), ceiling)


@dataclass
class RolloutResult(TaskEpisodes):
    """Per-episode records of a :func:`rollout`."""

    cfg: WorldConfig
    n_robots: int
    seed: int | None
    rewards: np.ndarray  # (E, T) float64 team reward per step
    success: np.ndarray  # (E, T) float64 the task's success after each step
    trajectories: Trajectories | None = None
    extra: dict = field(default_factory=dict)
    emitter: np.ndarray | None = None  # (E, 2) float64 mm, the emitter at the end of each episode (None: no emitter)
    task: Any = None  #: the env's task (sim.tasks.Task): its metrics; None: localisation


def robot_success(info, n_envs: int, n_robots: int) -> np.ndarray:
    """(B, M) bool: the robots the task counts as successful this step (its ``robot_success`` info entry,
    all False when it has none); plots and animations highlight them."""
    flags = info.get("robot_success")
    return np.zeros((n_envs, n_robots), bool) if flags is None else flags


class EpisodeLoop:
    """The one stepping loop: batches of ``env.n_envs`` synchronised episodes of ``env.cfg.episode_steps`` steps.

    :meth:`begin` resets the env (a seed, or None to go on with its streams); :meth:`step` sends the commands
    (``send``: ``env.step`` by default, ``env.step_u8`` for the firmware's uint8 commands) and keeps, in the
    rows of the current batch, each step's team reward and the task's success (``info["success"]``) in
    ``rewards`` and ``success`` (E, T) and the episodes' running ``returns`` (E,), summed step by step.
    Batch k fills row block ``k % batches`` (``batches=1``: every batch reuses the same rows).
    :meth:`run` drives whole batches from a policy callback; learners that step several envs in
    lockstep call :meth:`begin` and :meth:`step` themselves.
    """

    def __init__(self, env, batches: int = 1, send: Callable | None = None) -> None:
        assert batches >= 1, f"batches must be >= 1, got {batches}"
        self.env = env
        self.batches = int(batches)
        self.send = env.step if send is None else send
        B, M, T = env.n_envs, env.n_robots, env.cfg.episode_steps
        self.steps = T
        self.shape = (B, M, ACTION_DIM)
        self.rewards = np.zeros((self.batches * B, T))
        self.success = np.zeros((self.batches * B, T))
        self.returns = np.zeros(self.batches * B)
        self.k = -1  #: the current batch
        self.t = 0  #: steps taken in it
        self.rows = slice(0, B)  #: its rows of the records

    def begin(self, seed: Any = None):
        """Start the next batch: ``env.reset(seed)``; returns its (obs, info)."""
        self.k += 1
        B = self.shape[0]
        b = self.k % self.batches
        self.rows = slice(b * B, (b + 1) * B)
        self.t = 0
        self.returns[self.rows] = 0.0
        return self.env.reset(seed=seed)

    def step(self, a: np.ndarray):
        """Send commands ``a`` (B, M, 2), record the step; returns (obs, reward, truncated, info)."""
        assert a.shape == self.shape, f"policy returned {a.shape}, expected {self.shape}"
        obs, r, _, truncated, info = self.send(a)
        t, rows = self.t, self.rows
        self.rewards[rows, t] = r
        self.success[rows, t] = info["success"]
        self.returns[rows] += r
        self.t = t + 1
        if self.t == self.steps:
            assert np.all(truncated), "env did not truncate after cfg.episode_steps steps"
        return obs, r, truncated, info

    def run(self, act: Callable, seeds: Iterable = (None,), begin: Callable | None = None,
            observe: Callable | None = None, end: Callable | None = None) -> "EpisodeLoop":
        """One batch per seed (``seeds`` may be a lazy iterable: each is drawn just before its reset).

        ``act(t, obs, info)`` gives the commands of step t; hooks: ``begin(k, obs, info)`` after batch k's reset,
        ``observe(t, a, obs, reward, info)`` after each step, ``end(k)`` after the batch's last step.
        """
        T = self.steps
        for seed in seeds:
            obs, info = self.begin(seed)
            if begin is not None:
                begin(self.k, obs, info)
            for t in range(T):
                a = act(t, obs, info)
                obs, r, _, info = self.step(a)
                if observe is not None:
                    observe(t, a, obs, r, info)
            if end is not None:
                end(self.k)
        return self


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
    env_seeds, pol_seqs = [], []
    for ss in np.random.SeedSequence(seed).spawn(n_batches):
        env_ss, pol_ss = ss.spawn(2)
        env_seeds.append(int(env_ss.generate_state(1, np.uint32)[0]))
        pol_seqs.append(pol_ss)

    n_rec = episodes if record is True else max(0, min(int(record), episodes))
    rec_batches = math.ceil(n_rec / B)  # record whole batches, trim at the end
    has_emitter = env.cfg.emitter
    emitter = np.zeros((n_batches * B, 2)) if has_emitter else None
    if n_rec:
        pos = np.zeros((rec_batches * B, T + 1, M, 2), np.float32)
        head = np.zeros((rec_batches * B, T + 1, M), np.float32)
        tgt = np.zeros((rec_batches * B, T + 1, 2), np.float32) if has_emitter else None
        inr = np.zeros((rec_batches * B, T + 1, M), bool)
        acts = np.zeros((rec_batches * B, T, M, 2), np.float32)
    loop = EpisodeLoop(env, n_batches)

    def begin(k: int, obs, info) -> None:
        policy.reset(B, M, np.random.default_rng(pol_seqs[k]))
        if k < rec_batches:
            rows = loop.rows
            pos[rows, 0] = env.pos
            head[rows, 0] = env.heading
            if has_emitter:
                tgt[rows, 0] = env.target
            inr[rows, 0] = robot_success(info, B, M)

    def act(t: int, obs, info) -> np.ndarray:
        return np.asarray(policy.act(obs), np.float64)

    def observe(t: int, a, obs, r, info) -> None:
        if loop.k < rec_batches:
            rows = loop.rows
            pos[rows, t + 1] = env.pos
            head[rows, t + 1] = env.heading
            if has_emitter:
                tgt[rows, t + 1] = env.target
            inr[rows, t + 1] = robot_success(info, B, M)
            acts[rows, t] = a
        if bar is not None:
            bar.update(1)

    def end(k: int) -> None:
        emitter[loop.rows] = env.target

    bar = None
    if progress:
        from kiloforge.progress import progress_bar

        bar = progress_bar(total=n_batches * T, unit="step", desc=f"{episodes} episodes", leave=False)
    try:
        loop.run(act, env_seeds, begin, observe if (n_rec or bar is not None) else None, end if has_emitter else None)
    finally:
        if bar is not None:
            bar.close()

    traj = None
    if n_rec:
        traj = Trajectories(pos[:n_rec], head[:n_rec], None if tgt is None else tgt[:n_rec], inr[:n_rec], acts[:n_rec])
    return RolloutResult(cfg=cfg, n_robots=M, seed=seed, rewards=loop.rewards[:episodes],
                         success=loop.success[:episodes], trajectories=traj,
                         emitter=None if emitter is None else emitter[:episodes], task=env.task)
