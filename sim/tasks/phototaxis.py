"""Phototaxis: robots gather in the lit spot under a lamp (Ben Zion et al., *Science Robotics* 2023: 64
Kilobots, a spot of about 6 % of the arena; ../shared/reference/swarm-tasks.md). No beacon.

*World* (:meth:`Phototaxis.world`): a lamp above the table lights a spot of nominal radius
:data:`SPOT_RADIUS_MM` at the arena's centre, with a soft edge :data:`SPOT_EDGE_MM` wide (half the lamp's
:data:`SPOT_PEAK` counts at the nominal radius, :mod:`sim.light`), over an unlit floor (walls unlit:
``light_wall = light_floor``); the sensor model's noise, per-robot gain and offset spreads are
assumptions (:data:`SENSOR`), its range and -1 while receiving are the Kilobot's. A world that already
has lamps keeps them (its first ``spot`` lamp is the spot). Observation: the graded ``light`` feature
(held level and its change) and the RBF histogram; no wall flag (the walls are not lit).

*Arena per swarm size* (:meth:`Phototaxis.world_for`): 16 and 32 robots run in the world's arena
(the kilobot preset's 500 mm); more than 32 robots run in the anchor's geometry, an arena whose area
is the spot's / :data:`ANCHOR_SPOT_FRACTION` (6 %: 724 mm wide for the 100 mm spot). ``learn evaluate
--robots 16 32 64`` and ``python -m sim`` make each size's world so.

*Success* of a step: the fraction of robots whose centre is within the spot's nominal radius of the
spot's centre (following the lamp where a variant moves it); the primary metric is its mean over the last
quarter of the episode. Team reward: ``scale * (success² - penalty · (1/M) Σ_i ||a_i||²)``.

*Ceiling*: ``min(M, capacity) / M`` where ``capacity`` is how many 33 mm discs we can place with their
centres in the spot (:func:`spot_capacity`, the best hexagonal lattice over offsets: a packing we found,
so a lower bound on the true maximum, as localisation's packing ceiling is).

*Baselines* (tuned on validation episodes, seed 777, ``python -m tools.tune_phototaxis``):
:class:`StopInLight` (walk; stop while the reading is above a threshold) and :class:`RunAndTumble` (straight
while the reading does not fall, a random turn when it falls by more than a margin or, rarely, at random), both from the
``light`` feature only, and the random walk.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kiloforge.errors import InputError

from ..baselines import COUNTER_MAX, check_fields
from ..config import ACTION_DIM, WorldConfig
from ..light import ADC_MAX
from .base import BeaconlessTask, Metric

SPOT_RADIUS_MM = 100.0  #: the spot's nominal radius (half intensity; "inside" = centre within it)
SPOT_EDGE_MM = 40.0  #: width of the soft edge, centred on the nominal radius
SPOT_PEAK = 600  #: ADC counts the lamp adds in the spot (over the floor)
ANCHOR_SPOT_FRACTION = 0.06  #: Ben Zion et al.: the spot is about 6 % of the arena
#: sensor model (assumptions, sim.light): noise std per reading, per-robot gain spread, offset spread (counts)
SENSOR = {"light_noise": 8.0, "light_gain_spread": 0.1, "light_offset_spread": 20.0}
HEX_OFFSETS = 24  #: lattice offsets tried per cell axis by spot_capacity


def spot_capacity(radius_mm: float, diameter_mm: float, offsets: int = HEX_OFFSETS) -> int:
    """Discs of ``diameter_mm`` with centres within ``radius_mm`` of a point: the most points of a hexagonal
    lattice of spacing ``diameter_mm`` inside that disc over ``offsets``² lattice offsets (a packing, so a
    lower bound on the maximum; rotations are not needed: the disc is round). 7 at radius = diameter."""
    d = float(diameter_mm)
    n = int(math.ceil(radius_mm / d)) + 2
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    base = np.stack([(i + 0.5 * j) * d, j * d * math.sqrt(3) / 2], -1).reshape(-1, 2)
    u = np.arange(offsets) / offsets
    ou, ov = np.meshgrid(u, u)
    off = np.stack([(ou + 0.5 * ov) * d, ov * d * math.sqrt(3) / 2], -1).reshape(-1, 1, 2)  # over one cell
    r2 = (base[None] + off) ** 2
    return int(((r2[..., 0] + r2[..., 1]) <= radius_mm ** 2 * (1 + 1e-12)).sum(axis=1).max())


def spot_of(cfg: WorldConfig):
    """The world's spot: its first ``spot`` lamp (None when it has none)."""
    return next((lamp for lamp in cfg.lamp_list if lamp.kind == "spot"), None)


class Phototaxis(BeaconlessTask):
    name = "phototaxis"
    version = 1
    description = "robots gather in the lit spot under a lamp (no beacon; light and neighbour distances)"
    success_label = "fraction of robots in the spot"
    robot_label = "in the spot"
    primary_metric = "final_in_spot"
    mean_metric = "mean_in_spot"
    metrics = (Metric("final_in_spot", "final in spot", name="final fraction in the spot"),
               Metric("of_ceiling", "of ceiling", bounded=True),
               Metric("mean_in_spot", "mean in spot"),
               Metric("return", "return"))
    baselines = {"hand-written stop-in-light": "stop_in_light", "hand-written run-and-tumble": "run_and_tumble",
                 "random": "random"}
    beacon = False
    features = ("light", "rbf")

    def world(self, cfg: WorldConfig) -> WorldConfig:
        """The task's layout; a world without lamps gets the spot lamp, unlit walls and the sensor model."""
        cfg = super().world(cfg)
        if cfg.lamps:
            return cfg
        spot = f"spot:0,0,{SPOT_RADIUS_MM:g},{SPOT_EDGE_MM:g},{SPOT_PEAK}"
        return dataclasses.replace(cfg, lamps=spot, light_wall=cfg.light_floor, **SENSOR)

    def check_world(self, cfg: WorldConfig) -> None:
        super().check_world(cfg)
        if spot_of(cfg) is None:
            raise InputError(f"world '{cfg.name}' has no spot lamp (lamps {cfg.lamps!r}); task 'phototaxis' gathers "
                             "robots in one: add spot:x,y,radius,edge,peak (Task.world(cfg) makes the default)")

    def world_for(self, cfg: WorldConfig, n_robots: int) -> WorldConfig:
        """More than 32 robots: the anchor's arena, the spot's area / 6 % (module doc); else ``cfg``."""
        if n_robots <= 32:
            return cfg
        spot = spot_of(cfg)
        half = round(math.sqrt(math.pi * spot.radius ** 2 / ANCHOR_SPOT_FRACTION) / 2)
        return cfg if half <= cfg.arena_half_mm else dataclasses.replace(cfg, arena_half_mm=float(half))

    def spot_centre(self, env) -> np.ndarray:
        """(B, 2) each env's spot centre (moved with the lamps where the randomisation shifts them)."""
        spot = spot_of(env.cfg)
        c = np.broadcast_to(np.array([spot.x, spot.y]), (env.n_envs, 2))
        shift = env.world_draw.lamp_shift_mm
        return c if shift is None else c + shift

    def step_info(self, env) -> dict[str, np.ndarray]:
        d = env.pos - self.spot_centre(env)[:, None, :]
        inside = np.hypot(d[..., 0], d[..., 1]) <= spot_of(env.cfg).radius
        return {"success": inside.mean(axis=1), "robot_success": inside}

    def make_baseline(self, name: str, cfg: WorldConfig) -> Any:
        if name == "stop_in_light":
            return StopInLight(cfg)
        if name == "run_and_tumble":
            return RunAndTumble(cfg)
        from ..baselines import make_policy

        return make_policy(name, cfg)

    def has_ceiling(self, cfg: WorldConfig) -> bool:
        """The spot's disc capacity, in collision worlds (discs)."""
        return cfg.collisions and cfg.robot_radius_mm > 0

    def ceiling(self, cfg: WorldConfig, n_robots: int) -> float:
        """``min(M, capacity) / M`` (module doc)."""
        cap = spot_capacity(spot_of(cfg).radius, 2.0 * cfg.robot_radius_mm)
        return min(n_robots, cap) / n_robots

    def episode_metrics(self, cfg: WorldConfig, n_robots: int, rewards: np.ndarray, success: np.ndarray,
                        beacon: np.ndarray | None, ceiling: bool = False) -> Any:
        from ..metrics import success_metrics

        c = np.full(len(success), self.ceiling(cfg, n_robots)) if ceiling else None
        return success_metrics(rewards, success, self.primary_metric, self.mean_metric, ceiling=c)


#: what the baselines' parameters may be: readings and their change in ADC counts, the mean run a 16-bit
#: probability 1 / run_steps, the pivots a uint8 counter (the firmware's fields; the simulator accepts the same)
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "threshold": (0, ADC_MAX), "fall": (0, ADC_MAX), "run_steps": (1, 0xFFFF), "turn_max_steps": (1, COUNTER_MAX)}


@dataclass(frozen=True)
class StopInLightParams:
    """Constants of :class:`StopInLight`, tuned by ``python -m tools.tune_phototaxis`` (seed 777: 0.920 at 16 robots).
    Each is checked against :data:`PARAM_RANGES` (InputError naming it and its range)."""

    threshold: int = 550  #: stop while the held reading is at least this (ADC counts)
    run_steps: int = 5  #: mean straight run of the walk outside the light (periods, geometric)
    turn_max_steps: int = 2  #: a random turn pivots 1..this many periods

    def __post_init__(self) -> None:
        check_fields(self, PARAM_RANGES, "stop_in_light")


@dataclass(frozen=True)
class RunAndTumbleParams:
    """Constants of :class:`RunAndTumble`, tuned by ``python -m tools.tune_phototaxis`` (seed 777: 0.515 at 16 robots).
    Each is checked against :data:`PARAM_RANGES`."""

    fall: int = 12  #: tumble when the reading fell by more than this since the last period (ADC counts)
    run_steps: int = 40  #: otherwise tumble with probability 1 / this per period (so walls do not trap it)
    turn_max_steps: int = 6  #: a tumble pivots 1..this many periods

    def __post_init__(self) -> None:
        check_fields(self, PARAM_RANGES, "run_and_tumble")


def tumble_prob(p: StopInLightParams | RunAndTumbleParams) -> float:
    """P(a random turn starts) per period: geometric runs of mean ``run_steps``."""
    return 1.0 / p.run_steps


def stops(p: StopInLightParams, level: np.ndarray) -> np.ndarray:
    """StopInLight stands where the held reading ``level`` (ADC counts) is at least the threshold."""
    return level >= p.threshold


def falls(p: RunAndTumbleParams, change: np.ndarray) -> np.ndarray:
    """RunAndTumble tumbles where the reading's ``change`` (ADC counts) fell by more than ``fall``."""
    return change < -p.fall


class LightWalker:
    """The shared walk of the light baselines: straight, or a pivot of 1..k periods in a random direction;
    reads the ``light`` feature (level and change in counts / 1024). Vectorised over (B, M). Its random
    numbers come from :meth:`draws` (the firmware's twin draws them from xorshift32: kiloforge/actors/light_rules.py)."""

    def __init__(self, cfg: WorldConfig) -> None:
        self.cfg = cfg
        self.i = cfg.obs_index("light")
        self.rng: np.random.Generator | None = None

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng
        self.turn_left = np.zeros((n_envs, n_robots), np.int64)  # pivot periods still to do
        self.turn_dir = np.zeros((n_envs, n_robots), bool)  # True: left

    def counts(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(level, change) in ADC counts."""
        return obs[..., self.i] * 1024.0, obs[..., self.i + 1] * 1024.0

    def draws(self, shape: tuple[int, ...], turn_max: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One period's draws: uniform [0, 1) for a random turn, its pivot periods (1..turn_max), its direction
        (True: left)."""
        assert self.rng is not None, "act before reset"
        u = self.rng.random(shape)
        return u, self.rng.integers(1, turn_max + 1, shape), self.rng.random(shape) < 0.5

    def walk(self, stop: np.ndarray, tumble: np.ndarray, steps: np.ndarray, left: np.ndarray) -> np.ndarray:
        """Actions: stopped robots stand; others start a turn of ``steps`` pivots towards ``left`` where ``tumble``
        (unless turning), else drive on."""
        shape = stop.shape
        start = tumble & (self.turn_left == 0) & ~stop
        self.turn_left = np.where(start, steps, self.turn_left)
        self.turn_dir = np.where(start, left, self.turn_dir)
        turning = ~stop & (self.turn_left > 0)
        a = np.zeros(shape + (ACTION_DIM,))
        a[~stop & ~turning] = 1.0
        a[..., 0] = np.where(turning & ~self.turn_dir, 1.0, a[..., 0])  # right pivot: left motor on
        a[..., 1] = np.where(turning & self.turn_dir, 1.0, a[..., 1])
        self.turn_left = np.where(turning, self.turn_left - 1, self.turn_left)
        return a


class StopInLight(LightWalker):
    """Stop while the reading is above a threshold; elsewhere a random walk (straight runs, random turns)."""

    def __init__(self, cfg: WorldConfig, params: StopInLightParams | None = None) -> None:
        super().__init__(cfg)
        self.p = params or StopInLightParams()

    def act(self, obs: np.ndarray) -> np.ndarray:
        level, _ = self.counts(obs)
        u, steps, left = self.draws(level.shape, self.p.turn_max_steps)
        return self.walk(stops(self.p, level), u < tumble_prob(self.p), steps, left)


class RunAndTumble(LightWalker):
    """Straight while the reading rises or holds; a turn of a random 1..k periods when it falls (and, as a
    bacterium's run-and-tumble, now and then at random, so a robot against a wall gets away)."""

    def __init__(self, cfg: WorldConfig, params: RunAndTumbleParams | None = None) -> None:
        super().__init__(cfg)
        self.p = params or RunAndTumbleParams()

    def act(self, obs: np.ndarray) -> np.ndarray:
        _, change = self.counts(obs)
        u, steps, left = self.draws(change.shape, self.p.turn_max_steps)
        return self.walk(np.zeros(change.shape, bool), falls(self.p, change) | (u < tumble_prob(self.p)), steps, left)
