"""SwarmEnv: B synchronised swarm worlds of M robots and a task's bodies (:mod:`sim.tasks`), on NumPy arrays.

One control period per :meth:`SwarmEnv.step`:

1. **Act.** Thesis worlds: the thesis kinematics on the float command (:func:`sim.kinematics.thesis_move`).
   Tick-level worlds: the command is quantised to uint8 (:func:`sim.motion.action_to_u8`) and the
   motor schedule runs tick by tick (:func:`sim.kinematics.tick_move`). Walls clip; discs in
   collision worlds are pushed apart, the emitter's disc too (``cfg.emitter_mobility``: 0 =
   fixed, 1 = pushed like a robot); an emitter riding on a heavy body (``cfg.body_radius_mm > 0``) takes no
   part in that: the body settles once per period after the moves (:mod:`sim.body`). Everything that
   follows uses the emitter's current position.
2. **Hear.** The radio stage of :mod:`sim.radio` (thesis or tick-level mode) gives the period's
   messages; messages carry each sender's ``sensing`` flag of its last control step.
3. **Observe.** Light at the control tick, then :func:`sim.events.observe` (or its bit-identical
   fast path) gives the observation and each robot's new ``sensing`` flag.
4. **Task.** The task (:class:`sim.tasks.Task`, default localisation) gives the step's ``info``
   entries, among them ``success`` (B,), and the team reward from the command actually applied
   (the float action in thesis worlds, q / 255 in tick-level worlds and in :meth:`step_u8`).

Domain randomisation (``randomise=``, :mod:`sim.variants`): each env draws its own speed, turn
rates, per-robot calibration, motor model, message period and success, distance noise, light
zones and emitter mobility at every reset, from its init stream after the spawn.

Random numbers: every env owns three generators (init, radio, light) from its own
``SeedSequence``; env e of ``SwarmEnv(..., seed=s)`` uses ``SeedSequence(s, spawn_key=(e,))``
(= ``SeedSequence(s).spawn(B)[e]``), see :func:`env_seed_sequences`. So an env of a batch behaves
exactly like a single-env run seeded with that env's sequence, and the global NumPy RNG is never
used.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from kiloforge.errors import InputError
from kiloforge.xorshift import rng_seed, xorshift32

from . import compiled
from .config import WorldConfig
from .body import body_depth, push_body
from .kinematics import Collider, thesis_move, tick_move
from .motion import action_to_u8
from .variants import Randomisation, WorldDraw
from .radio import (RadioPeriod, draw_phases, light_readings, observe_period, target_distance,
                    thesis_radio, tick_radio)
from .tasks import Task, get_task
from .features import emitter_sends_light, held_light, held_object_light
from .light import draw_sensors

ACTION_TOL = 1e-6  #: actions may exceed [0, 1] by this much (then they are clipped)
MAX_PACKING = 0.45  #: collision worlds refuse to spawn more disc area than this fraction of the arena
#: per-env random streams (children of the env's seed sequence in this order); "emitter_light" (the emitter's own
#: light sensor) is drawn only in worlds with ``object_light``
_STREAMS = ("init", "radio", "light", "emitter_light")



def _child(ss: np.random.SeedSequence, k: int) -> np.random.SeedSequence:
    """The k-th child of ``ss`` without mutating it (same as a fresh ``ss.spawn(k + 1)[k]``)."""
    return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (k,), pool_size=ss.pool_size)


def env_seed_sequences(seed: Any, n_envs: int) -> list[np.random.SeedSequence]:
    """Per-env seed sequences: env e gets ``SeedSequence(seed, spawn_key=(e,))``.

    ``seed`` may be None (fresh OS entropy), a non-negative int, a ``SeedSequence`` (its children
    are used) or a list of exactly ``n_envs`` SeedSequences (used as they are: this is how one env
    of a batch is replayed alone, ``SwarmEnv(cfg, 1, M, seed=[env_seed_sequences(s, B)[e]])``).
    """
    if isinstance(seed, (list, tuple)):
        if len(seed) != n_envs or not all(isinstance(s, np.random.SeedSequence) for s in seed):
            raise ValueError(f"a seed list must hold exactly n_envs={n_envs} numpy SeedSequences")
        return list(seed)
    if isinstance(seed, np.random.SeedSequence):
        root = seed
    elif seed is None:
        root = np.random.SeedSequence()
    elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0:
        root = np.random.SeedSequence(int(seed))
    else:
        raise ValueError(f"seed must be None, a non-negative int or SeedSequence(s), got {seed!r}")
    return [_child(root, e) for e in range(n_envs)]


class StepInfo(dict):
    """The ``info`` dict. Lazy entries (``events``) are computed on first access and then kept."""

    def __init__(self, lazy: dict[str, Callable[[], Any]], **items: Any) -> None:
        super().__init__(**items)
        self._lazy = dict(lazy)

    def _load(self, key: Any) -> None:
        fn = self._lazy.pop(key, None)
        if fn is not None:
            dict.__setitem__(self, key, fn())

    def _load_all(self) -> None:
        for k in list(self._lazy):
            self._load(k)

    def __getitem__(self, key: Any) -> Any:
        self._load(key)
        return dict.__getitem__(self, key)

    def get(self, key: Any, default: Any = None) -> Any:
        self._load(key)
        return dict.get(self, key, default)

    def __contains__(self, key: object) -> bool:
        return key in self._lazy or dict.__contains__(self, key)

    def __len__(self) -> int:
        return dict.__len__(self) + len(self._lazy)

    def __iter__(self):
        self._load_all()
        return dict.__iter__(self)

    def keys(self):
        self._load_all()
        return dict.keys(self)

    def values(self):
        self._load_all()
        return dict.values(self)

    def items(self):
        self._load_all()
        return dict.items(self)

    def pop(self, key: Any, *default: Any) -> Any:
        self._load(key)
        return dict.pop(self, key, *default)

    def __setitem__(self, key: Any, value: Any) -> None:
        self._lazy.pop(key, None)
        dict.__setitem__(self, key, value)

    def __delitem__(self, key: Any) -> None:
        self._load(key)
        dict.__delitem__(self, key)

    def copy(self) -> dict:
        self._load_all()
        return dict(self)

    def __repr__(self) -> str:
        self._load_all()
        return dict.__repr__(self)

    def __reduce__(self):
        self._load_all()
        return (dict, (dict(self),))


class SwarmEnv:
    """B synchronised envs of M searchers and a target (see the module doc for one step).

    Attributes: ``pos`` (B, M, 2) mm, ``heading`` (B, M) rad in (-π, π], ``target`` (B, 2) mm (the
    emitter's current position: collisions push it when ``cfg.emitter_mobility > 0``; None when the task
    has no emitter: then nothing but the robots transmits or collides),
    ``t`` steps done this episode, ``sensing`` (B, M) uint8, ``cfg``, ``n_envs``, ``n_robots``.
    ``randomise`` (:class:`sim.variants.Randomisation`): domain randomisation, every env drawing its
    own world parameters at every reset from its init stream (``world_draw`` holds them).
    ``fast_observe=False`` forces the general events path (for tests); ``neighbour_method``
    ('auto', 'dense', 'grid') picks the neighbour search. ``task``: a :class:`sim.tasks.Task` or
    anything :func:`sim.tasks.get_task` resolves (default: localisation).
    """

    def __init__(self, cfg: WorldConfig, n_envs: int, n_robots: int, seed: Any = None, *,
                 randomise: Randomisation | None = None, fast_observe: bool = True,
                 neighbour_method: str = "auto", task: "Task | str | None" = None) -> None:
        if not isinstance(cfg, WorldConfig):
            raise ValueError(f"cfg must be a WorldConfig (e.g. sim.config.preset('thesis')), got {type(cfg).__name__}")
        for name, v in (("n_envs", n_envs), ("n_robots", n_robots)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if neighbour_method not in ("auto", "dense", "grid"):
            raise ValueError(f"neighbour_method must be auto, dense or grid, got {neighbour_method!r}")
        if randomise is not None:
            if not isinstance(randomise, Randomisation):
                raise ValueError(f"randomise must be a sim.variants.Randomisation, got {type(randomise).__name__}")
            randomise.check(cfg)
        self.cfg = cfg
        self.task = get_task(task)
        self.task.check_world(cfg)
        self.randomise = randomise
        self.world_draw = WorldDraw()  #: this episode's drawn parameters (all None without randomise)
        self.n_envs, self.n_robots = int(n_envs), int(n_robots)
        self.fast_observe = fast_observe
        self.neighbour_method = neighbour_method
        self._check_spawn_room()
        self._collider = Collider(cfg) if cfg.collisions and cfg.robot_radius_mm > 0 else None
        self._mobility: float | np.ndarray = cfg.emitter_mobility  # scalar, or (B,) per env
        self._mobile = False  # some env's emitter can be pushed (set at reset)
        self._seed(seed)
        self.pos: np.ndarray | None = None
        self.heading: np.ndarray | None = None
        self.target: np.ndarray | None = None
        self.sensing: np.ndarray | None = None
        self.target_dist: np.ndarray | None = None  # (B, M) true robot-emitter distance after the last move
        self.phase: np.ndarray | None = None  # (B, M + 1) transmit phases (tick-level radio)
        self.t = 0
        self._started = False

    # --- properties ----------------------------------------------------------------------------
    @property
    def obs_dim(self) -> int:
        return self.cfg.obs_dim

    @property
    def state_dim(self) -> int:
        return self.task.state_dim(self.cfg, self.n_robots)

    @property
    def _heavy_body(self) -> bool:
        """True when the emitter rides on a heavy body robots push together (:mod:`sim.body`)."""
        return self.cfg.body_radius_mm > 0 and self.target is not None

    @property
    def _disc_body(self) -> np.ndarray | None:
        """The emitter as a disc of the per-tick contacts (None without one, or when it rides on a heavy body)."""
        return None if self._heavy_body else self.target

    @property
    def _pushable(self) -> bool:
        """True when collisions can move the emitter (so the radio needs its position per tick)."""
        return self._collider is not None and self._disc_body is not None and self._mobile

    @property
    def tick_level_radio(self) -> bool:
        """True when messages follow the tick-level model (``msg_period_ticks >= 1``)."""
        return self.cfg.msg_period_ticks >= 1

    # --- seeding and spawning ------------------------------------------------------------------
    def _seed(self, seed: Any) -> None:
        seqs = env_seed_sequences(seed, self.n_envs)
        self.seed_sequences = seqs
        streams = [[np.random.default_rng(_child(ss, k)) for ss in seqs] for k in range(len(_STREAMS))]
        self._rng_init, self._rng_radio, self._rng_light, self._rng_emitter_light = streams

    @property
    def init_streams(self) -> list[np.random.Generator]:
        """Each env's init generator (spawn and domain randomisation draw from it, in that order)."""
        return self._rng_init

    def spawn_box(self) -> float:
        """Half side of the square robots and bodies spawn in."""
        return self.cfg.arena_half_mm - max(self.cfg.spawn_margin_mm, self.cfg.robot_radius_mm)

    def _check_spawn_room(self) -> None:
        cfg = self.cfg
        if self.spawn_box() <= 0:
            raise ValueError(f"no room to spawn: arena_half_mm {cfg.arena_half_mm} <= spawn margin / robot radius")
        if cfg.collisions and cfg.robot_radius_mm > 0:
            discs = self.n_robots + int(self.cfg.emitter)
            frac = discs * math.pi * cfg.robot_radius_mm ** 2 / (2 * self.spawn_box()) ** 2
            if frac > MAX_PACKING:
                side = math.sqrt(discs * math.pi * cfg.robot_radius_mm ** 2 / MAX_PACKING)
                raise ValueError(
                    f"{self.n_robots} robots of radius {cfg.robot_radius_mm} mm cover {frac:.0%} of the "
                    f"spawn area (max {MAX_PACKING:.0%}); use arena_half_mm >= {side / 2 + cfg.robot_radius_mm:.0f}")

    def _spawn(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bodies (B, 2), positions (B, M, 2), headings (B, M): the task's draw, then no overlaps."""
        target, pos, heading = self.task.spawn(self)
        if self.cfg.collisions and self.cfg.robot_radius_mm > 0:
            self._separate_spawn(pos, target, self.spawn_box())
        return target, pos, heading

    def _separate_spawn(self, pos: np.ndarray, target: np.ndarray | None, h: float) -> None:
        """Rejection: redraw (in index order, from the env's init stream) each robot that overlaps
        an earlier robot or the target (if any), until no disc overlaps (vectorised overlap test)."""
        from . import grid

        B, M = self.n_envs, self.n_robots
        diam = 2.0 * self.cfg.robot_radius_mm
        for _ in range(10_000):
            allpos = pos if target is None else np.concatenate([pos, target[:, None, :]], axis=1)  # (B, M [+ 1], 2)
            p = grid.pairs_within(allpos, diam, self.cfg.arena_half_mm)
            p_bad = p.dist < diam  # touching exactly is allowed
            bad = np.zeros((B, M), bool)
            if target is not None and self.cfg.body_radius_mm > 0:  # robots on the heavy body
                bad |= body_depth(pos, target, self.cfg)[0] > 0
                p_bad &= p.j != M
            if not (p_bad.any() or bad.any()):
                return
            redo = np.where(p.j[p_bad] == M, p.i[p_bad], p.j[p_bad])  # the later robot of the pair
            bad[p.env[p_bad], redo] = True
            for e in np.flatnonzero(bad.any(1)):  # loop over envs with overlaps
                idx = np.flatnonzero(bad[e])
                pos[e, idx] = self._rng_init[e].uniform(-h, h, (idx.size, 2))
        raise ValueError("could not place non-overlapping robots; enlarge arena_half_mm")

    # --- episode -------------------------------------------------------------------------------
    def reset(self, seed: Any = None) -> tuple[np.ndarray, StepInfo]:
        """Start new episodes in all envs; ``seed`` re-seeds as in the constructor."""
        if seed is not None:
            self._seed(seed)
        B, M = self.n_envs, self.n_robots
        self.target, self.pos, self.heading = self._spawn()
        if self.randomise is not None:  # after the spawn: spawns equal the nominal world's
            self.world_draw = self.randomise.draw(self.cfg, M, self._rng_init)
        w = self.world_draw
        self._mobility = self.cfg.emitter_mobility if w.emitter_mobility is None else w.emitter_mobility
        self._mobile = bool(np.any(np.asarray(self._mobility) > 0))  # some env's emitter can be pushed
        self.sensing = np.zeros((B, M), np.uint8)
        self._prev_wall = np.zeros((B, M), np.float32)
        self._light_held = np.full((B, M), -1, np.int16)  # the light feature's held reading (-1: none yet)
        self._sensors = draw_sensors(self.cfg, M, self._rng_light)  # per-robot light sensor gain and offset
        self._emitter_light = self._object_held = self._emitter_sensor = None
        if emitter_sends_light(self.cfg):  # the emitter reads the light and sends its held reading
            self._emitter_sensor = draw_sensors(self.cfg, 1, self._rng_emitter_light)
            self._emitter_light = np.full(B, -1, np.int64)  # none until its first control tick
            self._object_held = np.full((B, M), -1, np.int64)  # what each robot holds of it (-1: none yet)
        self._rand_word = self.rand_hard = None
        if self.cfg.has_feature("random"):  # last from the init stream: worlds without it draw as before
            self.rand_hard = np.stack([g.integers(0, 256, M) for g in self._rng_init]).astype(np.uint8)  # setup()'s rand_hard()
            uids = np.broadcast_to(np.arange(1, M + 1), (B, M))  # searcher i has kilo_uid i + 1
            self._rand_word = rng_seed(uids.ravel(), self.rand_hard.ravel()).reshape(B, M)
        self.t = 0
        self._tick0 = 0
        if self.tick_level_radio:
            self.phase = draw_phases(self._rng_radio, M, self.cfg, w.msg_period)
        P = self.cfg.period_ticks
        still = np.broadcast_to(self.pos, (P, B, M, 2)) if self.tick_level_radio else None  # no movement
        self.target_dist = self._target_distance()
        obs, info = self._sense(self._hear(still, self.target_dist))
        self._check_success(info)
        self._started = True
        return obs, info

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, StepInfo]:
        """Advance one control period with float actions (B, M, 2) in [0, 1]."""
        if not self.cfg.tick_level:
            return self._advance(self._check_actions(actions), None)
        q = None
        if compiled.available():  # checked and quantised in one compiled pass (None: the NumPy check says what is wrong)
            q = compiled.command_bytes(actions, (self.n_envs, self.n_robots, 2), -ACTION_TOL, 1.0 + ACTION_TOL)
        if q is None:
            q = action_to_u8(self._check_actions(actions))  # valid uint8 commands: step_u8's checks would pass
        return self._advance(q / 255.0, q)

    def step_u8(self, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, StepInfo]:
        """Advance one control period with uint8 motor commands (B, M, 2); u = q / 255."""
        q = np.asarray(commands)
        shape = (self.n_envs, self.n_robots, 2)
        if q.shape != shape:
            raise ValueError(f"commands must have shape (B, M, 2) = {shape}, got {q.shape}")
        if not np.issubdtype(q.dtype, np.integer):
            raise ValueError(f"commands must be uint8 motor commands 0..255, got dtype {q.dtype}; "
                             "use step() for float actions")
        if q.size and (q.min() < 0 or q.max() > 255):
            raise ValueError(f"commands must lie in 0..255, got min {q.min()}, max {q.max()}")
        q = q.astype(np.uint8)
        return self._advance(q / 255.0, q)

    # --- internals -----------------------------------------------------------------------------
    def _check_actions(self, actions: np.ndarray) -> np.ndarray:
        a = np.asarray(actions)
        shape = (self.n_envs, self.n_robots, 2)
        if a.shape != shape:
            raise ValueError(f"actions must have shape (B, M, 2) = {shape}, got {a.shape}")
        if a.dtype.kind not in "fiu":  # floats or integers
            raise ValueError(f"actions must be floats in [0, 1], got dtype {a.dtype}")
        a = np.asarray(a, np.float64)  # no copy for float64 input (never written to)
        lo, hi = float(np.minimum.reduce(a, axis=None)), float(np.maximum.reduce(a, axis=None))  # NaN propagates
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"actions contain {int(np.size(a) - np.isfinite(a).sum())} NaN/inf entries")
        if lo < -ACTION_TOL or hi > 1.0 + ACTION_TOL:
            raise ValueError(f"actions must lie in [0, 1], got min {lo:.6g}, max {hi:.6g}")
        return np.clip(a, 0.0, 1.0) if lo < 0.0 or hi > 1.0 else a

    def _advance(self, u: np.ndarray, q: np.ndarray | None):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self.t >= self.cfg.episode_steps:
            raise RuntimeError(f"the episode ended after {self.cfg.episode_steps} steps; call reset()")
        cfg = self.cfg
        B, M = self.n_envs, self.n_robots
        record = emitter = None
        P = cfg.period_ticks
        if cfg.tick_level:
            assert q is not None
            if self.tick_level_radio:
                record = np.empty((P, B, M, 2))
                emitter = np.empty((P, B, 2)) if self._pushable else None
            tick_move(self.pos, self.heading, q, cfg, self._collider, self._disc_body, record,
                      target_record=emitter, motion=self.world_draw.motion, emitter_mobility=self._mobility)
        else:
            thesis_move(self.pos, self.heading, u, cfg)
            if self._collider is not None:
                self._collider.resolve(self.pos, self._disc_body, emitter_mobility=self._mobility)
        if self._heavy_body:  # once per period, after the robots' moves (sim.body)
            push_body(self.pos, self.target, cfg, self._collider)
            if record is not None:
                record[-1] = self.pos
        if not cfg.tick_level and self.tick_level_radio:  # thesis kinematics, tick-level radio: robots stand still
            record = np.broadcast_to(self.pos, (P, B, M, 2))
        self.target_dist = self._target_distance()
        obs, info = self._sense(self._hear(record, self.target_dist, emitter))
        reward = self.task.reward(self, u, info)
        self.t += 1
        self._tick0 += cfg.period_ticks
        truncated = np.full(B, self.t >= cfg.episode_steps)
        terminated = np.zeros(B, bool)
        return obs, reward, terminated, truncated, info

    def _target_distance(self) -> np.ndarray | None:
        """(B, M) true robot–emitter distances after the move (None without an emitter)."""
        return None if self.target is None else target_distance(self.pos, self.target)

    def _check_success(self, info: StepInfo) -> None:
        """A task's success signal must be (B,) values in [0, 1] (checked at every reset)."""
        s = np.asarray(info.get("success"))
        if s.shape != (self.n_envs,) or not np.issubdtype(s.dtype, np.number) or not np.all((s >= 0) & (s <= 1)):
            raise InputError(f"task '{self.task.name}': step_info()['success'] must be (B,) = ({self.n_envs},) "
                             f"values in [0, 1], got {s.dtype} {s.shape}")

    def _hear(self, record: np.ndarray | None, dt: np.ndarray, emitter: np.ndarray | None = None) -> RadioPeriod:
        if self.tick_level_radio:
            w = self.world_draw
            return tick_radio(record, self.target, self.phase, self._tick0, self.sensing, self.cfg,
                              self._rng_radio, self.neighbour_method, target_ticks=emitter,
                              msg_period=w.msg_period, msg_loss=w.msg_loss, dist_noise_mm=w.dist_noise_mm)
        return thesis_radio(self.pos, self.target, self.sensing, self.cfg, self._rng_radio, dt,
                            self.neighbour_method)

    def _emitter_reading(self) -> np.ndarray:
        """(B,) the emitter's ambient-light reading now: the robots' sensor model at the body's centre, on top of it,
        so unshaded (its own gain and offset, noise and dropout from its stream)."""
        return light_readings(self.target[:, None, :], self.cfg, self._rng_emitter_light, self.world_draw.wall_zone_mm,
                              self._emitter_sensor, self.world_draw)[:, 0].astype(np.int64)

    def _sense(self, period: RadioPeriod) -> tuple[np.ndarray, StepInfo]:
        light = light_readings(self.pos, self.cfg, self._rng_light, self.world_draw.wall_zone_mm, self._sensors,
                               self.world_draw, self.target if self._heavy_body else None)
        if self._rand_word is not None:  # the firmware steps its word once per control step
            self._rand_word = xorshift32(self._rand_word)
        if self._emitter_light is not None:  # this period's emitter messages carry its held reading
            period.t_light = self._emitter_light.take(period.t_env)
        obs, flags = observe_period(period, light, self._prev_wall, self.cfg, self.fast_observe, self._light_held,
                                    self._rand_word, self._object_held)
        if self.cfg.has_feature("light"):  # only the light feature reads the held reading
            self._light_held = held_light(light, self._light_held)
        if self._emitter_light is not None:
            heard = (flags > 0) & (self._emitter_light >= 0)[:, None]
            self._object_held = held_object_light(np.where(heard, self._emitter_light[:, None], -1), self._object_held)
            self._emitter_light = held_light(self._emitter_reading(), self._emitter_light)  # read at the control tick
        self.sensing = flags
        if self.cfg.has_feature("wall"):
            self._prev_wall = obs[..., self.cfg.obs_index("wall")].copy()
        info = StepInfo({"events": period.events}, light=light, **self.task.step_info(self))
        return obs, info

    def state(self) -> np.ndarray:
        """The task's critic state (B, state_dim) float32 (localisation: the emitter's xy, then each robot's x, y, φ)."""
        if not self._started:
            raise RuntimeError("call reset() before state()")
        return self.task.state(self)
