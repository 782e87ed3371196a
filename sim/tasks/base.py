"""The task interface: what a swarm task owns, apart from the world core (motion, contacts, radio).

A task is one class (one module per built-in task, or one file of a user's: docs/tasks.md). The
simulator's :class:`sim.env.SwarmEnv` asks its task, every episode and step, for

* the spawn: where robots (and the task's own bodies, e.g. localisation's beacon) start;
* the per-step information: the *success* signal, (B,) in [0, 1], that every table, plot and
  fitness aggregates (localisation: the fraction of robots within range of the beacon), and
  whatever else the task reports (``info`` entries);
* the team reward of the learners (MAGDDPG / MAGRDPG) and the centralised critic's state;

and the tools ask it for its metrics (names, labels, units, the primary one), its hand-written and
random baselines, and an optional upper bound on success (localisation's packing ceiling).

A task is identified by ``name`` and ``version`` (:class:`TaskRef`); a policy artifact records the
task it was trained for, and the tools refuse a policy of another task.
"""
from __future__ import annotations

import dataclasses
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from kiloforge.errors import InputError

from ..config import WorldConfig

TASK_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")  #: task names: short, lowercase, safe in C comments and file names
MAX_TASK_VERSION = 0xFFFF


@dataclass(frozen=True)
class TaskRef:
    """A task's identity as a policy artifact records it: ``{"name": ..., "version": ...}``."""

    name: str
    version: int

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and TASK_NAME.fullmatch(self.name)):
            raise InputError(f"task name must match {TASK_NAME.pattern} (lowercase letters, digits, _), "
                             f"got {self.name!r}")
        if not (isinstance(self.version, int) and not isinstance(self.version, bool)
                and 1 <= self.version <= MAX_TASK_VERSION):
            raise InputError(f"task version must be an integer in 1..{MAX_TASK_VERSION}, got {self.version!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version}

    def __str__(self) -> str:
        return f"{self.name} v{self.version}"


#: what a policy file written before tasks existed was trained for
LEGACY_TASK = TaskRef("localisation", 1)


@dataclass(frozen=True)
class Metric:
    """One scalar metric per episode, as tables, JSON and plots name it."""

    key: str  #: JSON key (evaluation.json, metrics.json)
    label: str  #: short column label in tables and plots
    unit: str = ""  #: "" for fractions and counts, e.g. "steps"
    higher_is_better: bool = True
    bounded: bool = False  #: only reported relative to the task's upper bound (``ceiling=True``)
    name: str = ""  #: a longer name for plot axes and logs (default: the label)

    @property
    def long(self) -> str:
        return self.name or self.label


class Task(ABC):
    """Base class of every task. Subclasses set the class attributes and implement the methods; ``env``
    is the :class:`sim.env.SwarmEnv` asking (its arrays, ``cfg``, ``n_envs``, ``n_robots``, ``init_streams``)."""

    name: ClassVar[str]  #: registry name, e.g. "localisation"
    version: ClassVar[int] = 1  #: bump when episodes of the same seed would differ
    description: ClassVar[str] = ""  #: one line for --help and docs
    success_label: ClassVar[str] = "success"  #: the per-step success signal as a plot axis names it
    robot_label: ClassVar[str] = "successful"  #: the robots ``robot_success`` highlights, as animations count them
    #: the file stem of the success-over-time plots the tools write (``coverage.png``, ``coverage_<M>.png``: the
    #: name they had before tasks existed, kept for every task)
    success_plot: ClassVar[str] = "coverage"
    primary_metric: ClassVar[str] = "final_success"  #: the metric key that ranks policies: final success
    mean_metric: ClassVar[str] = "mean_success"  #: the key of success averaged over the episode
    #: every scalar metric :meth:`episode_metrics` reports, primary first (tables show them in this order)
    metrics: ClassVar[tuple[Metric, ...]] = (Metric("final_success", "final"), Metric("mean_success", "mean"),
                                             Metric("return", "return"))
    #: baseline label -> name for :meth:`make_baseline`; labels start with "hand-written" or "random"
    baselines: ClassVar[dict[str, str]] = {}
    #: True: a beacon robot (kilo_uid ``cfg.emitter_uid``) that only transmits stands in the world (a disc in
    #: collision worlds), and the firmware gets its beacon role; False: only the M robots
    beacon: ClassVar[bool] = False
    #: what the beacon robot is, in messages to users (e.g. "the object's robot"); only with :attr:`beacon`
    beacon_role: ClassVar[str] = "the beacon"
    #: the task's firmware partials, a folder of firmware_templates/tasks/ (only with :attr:`beacon`): ``emitter.c.j2``,
    #: the C names and code of the beacon robot's role in the shared policy program, and ``program.c.j2``, that robot's
    #: own program (docs/tasks.md)
    firmware: ClassVar[str] = ""
    #: the file name the beacon robot's own program is written to (only with :attr:`beacon`; docs/flashing.md)
    emitter_program: ClassVar[str] = ""
    #: the observation: features of :mod:`sim.features` in input order (the world's ``obs_features``)
    features: ClassVar[tuple[str, ...]] = ("wall", "rbf")
    #: the task's own features (:class:`sim.table_features.TableFeature` subclasses), computed from the neighbour
    #: table; list their names in ``features`` to observe them (docs/tasks.md, "Your own feature")
    own_features: ClassVar[tuple[Any, ...]] = ()

    @property
    def ref(self) -> TaskRef:
        return TaskRef(self.name, self.version)

    def world(self, cfg: WorldConfig) -> WorldConfig:
        """``cfg`` with this task's emitter (:attr:`beacon`) and observation layout (every world a task runs in is made so)."""
        spec = ",".join(self.features)
        if cfg.emitter == self.beacon and cfg.obs_features == spec:
            return cfg
        return dataclasses.replace(cfg, emitter=self.beacon, obs_features=spec)

    def world_for(self, cfg: WorldConfig, n_robots: int) -> WorldConfig:
        """The world of a run with ``n_robots`` (default ``cfg``; a task whose geometry depends on the swarm size,
        e.g. phototaxis's arena for 64 robots, changes it). Evaluations and ``python -m sim`` ask per size."""
        return cfg

    def check_world(self, cfg: WorldConfig) -> None:
        """Raise InputError when the task cannot run in ``cfg``: an emitter or observation layout other than the
        task's (:meth:`world`). A subclass that adds conditions calls this first."""
        spec = ",".join(self.features)
        if cfg.emitter != self.beacon or cfg.obs_features != spec:
            raise InputError(f"world '{cfg.name}' has emitter {cfg.emitter} and observation {cfg.obs_features}; task "
                             f"'{self.name}' needs emitter {self.beacon} and observation {spec} (Task.world(cfg) makes it)")

    @abstractmethod
    def spawn(self, env: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Start positions from the env's init streams: the beacon (B, 2) (None when :attr:`beacon` is False),
        robots (B, M, 2), headings (B, M). The env then redraws overlapping robots (collision worlds)."""

    @abstractmethod
    def step_info(self, env: Any) -> dict[str, np.ndarray]:
        """The step's ``info`` entries after the move: ``success`` (B,) in [0, 1], and optionally
        ``robot_success`` (B, M) bool, the robots that count towards it (plots highlight them)."""

    @abstractmethod
    def reward(self, env: Any, u: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        """Team reward (B,) float32 of the step: ``u`` the applied commands (B, M, 2) in [0, 1]."""

    @abstractmethod
    def state_dim(self, cfg: WorldConfig, n_robots: int) -> int:
        """Width of :meth:`state`."""

    @abstractmethod
    def state(self, env: Any) -> np.ndarray:
        """The centralised critic's state (B, state_dim) float32."""

    def make_baseline(self, name: str, cfg: WorldConfig) -> Any:
        """The baseline ``name`` (a value of :attr:`baselines`) as a :class:`sim.rollout.SwarmPolicy`."""
        raise InputError(f"task '{self.name}' has no baseline '{name}'")

    def episode_metrics(self, cfg: WorldConfig, n_robots: int, rewards: np.ndarray, success: np.ndarray,
                        beacon: np.ndarray | None, ceiling: bool = False) -> Any:
        """Per-episode metrics (``summary()``, ``to_dict()``) of E episodes: team rewards and success (E, T), the
        beacon at each episode's end (E, 2) or None; ``ceiling``: also relative to the task's upper bound."""
        from ..metrics import success_metrics

        return success_metrics(rewards, success, self.primary_metric, self.mean_metric)

    @property
    def eval_keys(self) -> tuple[str, ...]:
        """The metrics a trainer's evaluations log (``eval_<key>`` columns), besides the return."""
        return tuple(m.key for m in self.metrics if m.key != "return" and not m.bounded)

    @property
    def columns(self) -> tuple[tuple[str, str], ...]:
        """(key, label) of every metric, for :func:`sim.metrics.compare`."""
        return tuple((m.key, m.label) for m in self.metrics)

    def has_ceiling(self, cfg: WorldConfig) -> bool:
        """True when the task reports an upper bound on final success in ``cfg`` (tables: "of ceiling")."""
        return False

    def no_ceiling_note(self, cfg: WorldConfig) -> str:
        """Why a task that has an upper bound has none in ``cfg`` (a note before tables without "of ceiling"); ""
        for a task that has none anywhere."""
        return ""

    def bound_report(self, cfg: WorldConfig) -> dict[str, Any]:
        """Top-level entries of ``evaluation.json`` about the upper bound in ``cfg`` (asked only when
        :meth:`has_ceiling`; default none)."""
        return {}

    def metric(self, key: str) -> Metric:
        for m in self.metrics:
            if m.key == key:
                return m
        raise KeyError(key)


# --- pieces several tasks share ------------------------------------------------------------------
def uniform_spawn(env: Any) -> tuple[None, np.ndarray, np.ndarray]:
    """No beacon; robots uniform over the spawn box, headings uniform, from each env's init stream."""
    import math

    from ..kinematics import wrap_angle

    B, M = env.n_envs, env.n_robots
    h = env.spawn_box()
    pos = np.empty((B, M, 2))
    heading = np.empty((B, M))
    for e, rng in enumerate(env.init_streams):  # loop over envs: each owns its generator
        pos[e] = rng.uniform(-h, h, (M, 2))
        heading[e] = rng.uniform(-math.pi, math.pi, M)
    return None, pos, wrap_angle(heading)


def squared_success_reward(env: Any, u: np.ndarray, success: np.ndarray) -> np.ndarray:
    """The thesis's §4.2 team reward on a task's success: ``scale * (s² - penalty · (1/M) Σ_i ||u_i||²)``."""
    cfg = env.cfg
    effort = np.sum(u * u, axis=(1, 2)) / env.n_robots
    return (cfg.reward_scale * (success * success - cfg.action_penalty * effort)).astype(np.float32)


def pose_state(env: Any) -> np.ndarray:
    """Critic state (B, 3M) of a task without a beacon: each robot's x, y / arena_half_mm and heading / π."""
    import math

    a, B, M = env.cfg.arena_half_mm, env.n_envs, env.n_robots
    robots = np.concatenate([env.pos / a, env.heading[..., None] / math.pi], axis=-1)
    return robots.reshape(B, 3 * M).astype(np.float32)


class BeaconlessTask(Task):
    """A task without a beacon whose robots spawn uniformly (:func:`uniform_spawn`), with the squared-success
    team reward (:func:`squared_success_reward`) and the robots' poses as the critic state (:func:`pose_state`):
    a subclass gives ``step_info`` and the class attributes."""

    beacon = False

    def spawn(self, env: Any) -> tuple[None, np.ndarray, np.ndarray]:
        return uniform_spawn(env)

    def reward(self, env: Any, u: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return squared_success_reward(env, u, info["success"])

    def state_dim(self, cfg: WorldConfig, n_robots: int) -> int:
        return 3 * n_robots

    def state(self, env: Any) -> np.ndarray:
        return pose_state(env)
