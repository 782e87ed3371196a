"""World variants a Kilobot user meets on a real table, and domain randomisation over them.

The nominal world (:class:`sim.config.WorldConfig`) is one idealised table. Real ones differ, and a
policy that only works on the nominal one will disappoint. Two tools:

* :func:`robustness_suite` — named variants, each ``(WorldConfig, Randomisation or None)``, that an
  evaluator runs one by one (:mod:`sim.robustness`);
* :class:`Randomisation` — distributions that a trainer hands to
  ``SwarmEnv(cfg, n_envs, n_robots, seed, randomise=...)``: at every reset each env draws its own
  parameters from its own init stream (after the spawn, so spawns equal the nominal world's; no
  global RNG; env e of a batch equals the single env with that seed sequence). Named presets:
  :data:`RANDOMISATIONS`. ``Randomisation()`` draws nothing and is the nominal world exactly.

What varies, and what it means physically:

Speed and turn rate (per env, ``speed``, ``turn``)
    The surface and the battery set how fast a calibrated Kilobot really goes and pivots:
    factors on ``v_max_mm_s`` and ``omega_max_rad_s``. The suite uses ±30 %.
Calibration spread (per robot, ``speed_spread``, ``turn_spread``, ``curve_deg_s``)
    Each robot is calibrated by hand (``kilo_straight_*``, ``kilo_turn_*``), so each has its own
    straight speed (relative std ``speed_spread``), its own left and right pivot rates
    (``turn_spread``, independently) and a "straight" that curves slightly (std ``curve_deg_s``
    degrees of heading per second of straight driving).
Motors (``motors``: ``"binary"``, ``"graded"`` or ``"mixed"``)
    The firmware only ever uses kilolib's calibrated modes: straight = both motors at their
    calibrated duty, pivot = one motor at its calibrated duty (:mod:`sim.motion`).
    *All-or-nothing* (``"binary"``, the nominal world, and how Kilombo models motors): a running
    motor gives exactly its calibrated effect, whatever the duty cycle's error, so only the
    per-robot factors above deviate. *Graded* (``"graded"``): a vibration motor's drive grows with
    its duty cycle, and the calibrated duty is only approximately right, so each wheel has its own
    relative drive ``w = 1 + wheel_spread · N(0, 1)``: straight speed ``(w_l + w_r) / 2``, a left
    pivot (left motor alone) ``w_l``, a right pivot ``w_r``, and on straights the stronger motor
    turns the robot towards the other side's pivot: heading rate ``(w_l - w_r) / 2 · ω_max``
    (counter-clockwise when the left motor is stronger). ``"mixed"``: each env draws one of the two.
Messages (per transmitter ``msg_period``, per env ``msg_success``)
    kilolib's transmit timer and each robot's clock give 15–17 ticks between messages rather than
    exactly 16; the floor and crowding make 60–100 % of messages arrive.
Distance noise (per env, ``dist_noise_mm``)
    ``estimate_distance`` scatter after calibration, 0–6 mm.
Ambient light (per env and wall, ``wall_zone``)
    The wall flag is the firmware's threshold on the light reading; lamps at the walls make the
    reading fall off with distance from a wall, so brighter light widens the zone where the flag is
    set and dimmer light narrows it. ``wall_zone`` is the zone width as a factor on
    ``wall_sense_mm``, drawn per wall (uneven light: one side brighter than the other). The suite
    also has dim (×0.5) and bright (×1.5) tables, uniformly.
Pivot point (per robot, ``pivot_offset_mm``)
    A Kilobot pivots about a leg (the nominal ``kilobot`` world, :mod:`sim.kinematics`), but on a
    slippery or uneven surface the leg slides and the effective pivot point lies closer to the
    centre: each robot's pivot distance from its centre is drawn uniformly, at the world's
    ``pivot_angle_deg``. The "table" randomisation spans centre (0) to leg (16.5 mm) pivots; the
    suite also runs the centre pivot alone.
Emitter (per env, ``emitter_mobility``)
    The task's transmitting robot taped down (0, the nominal ``kilobot`` world), or pushed by collisions
    like a robot (1).
Lamps (worlds with lamps only, :mod:`sim.light`; per env ``lamp_brightness``, ``lamp_shift_mm``,
``light_noise``)
    Lamp bulbs, their height and the room light differ from table to table, a lamp is never exactly
    where it was meant to be, and sensors are noisier in some rooms: a factor on every lamp's peak,
    a shift of every lamp in a random direction, and the sensor noise std. The suite has lamps
    dimmer (×0.6) and brighter (×1.4), moved 50 mm, and 30 counts more noise. Worlds without lamps
    draw none of these (their draws are as before).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .compat import EMITTER_FIXED_VARIANT, EMITTER_PUSHED_VARIANT, FREE_EMITTER_RANDOMISATION
from .config import KILOBOT, WorldConfig
from .kinematics import MotionParams

MOTORS = ("binary", "graded", "mixed")
MIN_FACTOR = 0.1  #: drawn speed / turn / wheel factors are clipped to at least this (no reversing motors)
Range = tuple[float, float]
LEG_PIVOT_MM = KILOBOT.pivot_offset_mm  #: the "leg pivot" variant of a centre-pivot world


@dataclass
class WorldDraw:
    """One reset's drawn parameters of a batch; None = the world config's value for everyone."""

    motion: MotionParams | None = None  #: per-robot motion factors (B, M)
    msg_period: np.ndarray | None = None  #: (B, M + 1) ticks between sends, per transmitter (M: the emitter)
    msg_loss: np.ndarray | None = None  #: (B,)
    dist_noise_mm: np.ndarray | None = None  #: (B,)
    wall_zone_mm: np.ndarray | None = None  #: (B, 4) wall-flag zone of the +x, +y, -x, -y walls
    emitter_mobility: np.ndarray | None = None  #: (B,)
    lamp_brightness: np.ndarray | None = None  #: (B,) factor on every lamp's peak
    lamp_shift_mm: np.ndarray | None = None  #: (B, 2) every lamp moved by this
    light_noise: np.ndarray | None = None  #: (B,) std of the light sensor's noise (ADC counts)


@dataclass(frozen=True)
class Randomisation:
    """Per-env (drawn at every reset) and per-robot parameter distributions; see the module doc.

    Ranges ``(lo, hi)`` are uniform (integers inclusive for ``msg_period``); None (or a zero
    spread) keeps the world config's value. The defaults change nothing.
    """

    speed: Range | None = None  #: factor on v_max_mm_s, per env
    turn: Range | None = None  #: factor on omega_max_rad_s, per env
    speed_spread: float = 0.0  #: per-robot relative std of the straight speed
    turn_spread: float = 0.0  #: per-robot relative std of the left and of the right pivot rate
    curve_deg_s: float = 0.0  #: per-robot std of the heading drift on straights, deg per second
    motors: str = "binary"  #: "binary" (all-or-nothing), "graded" or "mixed" (per env)
    wheel_spread: float = 0.0  #: graded motors: per-robot relative std of each wheel's drive
    msg_period: tuple[int, int] | None = None  #: ticks between sends, per transmitter
    msg_success: Range | None = None  #: fraction of messages received, per env
    dist_noise_mm: Range | None = None  #: std of the distance noise, per env
    wall_zone: Range | None = None  #: factor on wall_sense_mm, per env and wall
    emitter_mobility: Range | None = None  #: per env
    pivot_offset_mm: Range | None = None  #: pivot point's distance from the centre, per robot
    #: worlds with lamps only (:mod:`sim.light`; others draw nothing for these): per env
    lamp_brightness: Range | None = None  #: factor on every lamp's peak
    lamp_shift_mm: Range | None = None  #: distance the lamps are moved, in a uniformly random direction
    light_noise: Range | None = None  #: std of the light sensor's noise, ADC counts

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"Randomisation: {msg}")

        for name in ("speed", "turn", "msg_success", "dist_noise_mm", "wall_zone", "emitter_mobility", "pivot_offset_mm",
                     "lamp_brightness", "lamp_shift_mm", "light_noise"):
            r = getattr(self, name)
            need(r is None or (len(r) == 2 and 0 <= r[0] <= r[1]), f"{name} must be None or (lo, hi) with 0 <= lo <= hi, got {r}")
        for name in ("speed", "turn", "wall_zone"):
            r = getattr(self, name)
            need(r is None or r[0] > 0, f"{name} factors must be > 0, got {r}")
        need(self.msg_success is None or 0 < self.msg_success[0] and self.msg_success[1] <= 1,
             f"msg_success must lie in (0, 1], got {self.msg_success}")
        need(self.emitter_mobility is None or self.emitter_mobility[1] <= 1,
             f"emitter_mobility must lie in [0, 1], got {self.emitter_mobility}")
        need(self.msg_period is None or (len(self.msg_period) == 2 and 1 <= self.msg_period[0] <= self.msg_period[1] <= 255),
             f"msg_period must be (lo, hi) ticks with 1 <= lo <= hi <= 255, got {self.msg_period}")
        for name in ("speed_spread", "turn_spread", "curve_deg_s", "wheel_spread"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        need(self.motors in MOTORS, f"motors must be one of {', '.join(MOTORS)}, got {self.motors!r}")

    @property
    def moves(self) -> bool:
        """True when motion varies (needs a tick-level world)."""
        return (self.speed is not None or self.turn is not None or self.speed_spread > 0 or self.turn_spread > 0
                or self.curve_deg_s > 0 or (self.motors != "binary" and self.wheel_spread > 0)
                or self.pivot_offset_mm is not None)

    @property
    def radio(self) -> bool:
        """True when the radio varies (needs the tick-level radio)."""
        return self.msg_period is not None or self.msg_success is not None or self.dist_noise_mm is not None

    def check(self, cfg: WorldConfig) -> None:
        """Raise ValueError when this randomisation cannot apply to ``cfg``."""
        if self.moves and not cfg.tick_level:
            raise ValueError(f"motion variations need a tick-level world (e.g. preset 'kilobot'), not '{cfg.name}'")
        if self.radio and cfg.msg_period_ticks < 1:
            raise ValueError(f"radio variations need the tick-level radio (msg_period_ticks >= 1), not '{cfg.name}'")

    def draw(self, cfg: WorldConfig, n_robots: int, rngs: Sequence[np.random.Generator]) -> WorldDraw:
        """Each env's parameters from its own generator (a loop over envs, never over robots)."""
        M = n_robots
        per_env = [self._draw_env(cfg, M, rng) for rng in rngs]
        out = WorldDraw()
        if self.moves:
            sp, tl, tr, cu = (np.stack([d[k] for d in per_env]) for k in ("speed", "turn_left", "turn_right", "curve"))
            piv = np.stack([d["pivot_mm"] for d in per_env]) if self.pivot_offset_mm is not None else None
            out.motion = MotionParams(sp, tl, tr, cu if np.any(cu != 0) else None, piv)
        for key in ("msg_period", "msg_loss", "dist_noise_mm", "wall_zone_mm", "emitter_mobility", "lamp_brightness",
                    "lamp_shift_mm", "light_noise"):
            if key in per_env[0]:
                setattr(out, key, np.stack([d[key] for d in per_env]))
        return out

    def _draw_env(self, cfg: WorldConfig, M: int, rng: np.random.Generator) -> dict:
        """One env's draws, in a fixed order."""
        d: dict = {}
        if self.moves:
            s = rng.uniform(*self.speed) if self.speed is not None else 1.0
            w = rng.uniform(*self.turn) if self.turn is not None else 1.0
            speed = s * (1.0 + self.speed_spread * rng.standard_normal(M))
            left = w * (1.0 + self.turn_spread * rng.standard_normal(M))
            right = w * (1.0 + self.turn_spread * rng.standard_normal(M))
            curve = math.radians(self.curve_deg_s) * cfg.tick_s * rng.standard_normal(M)  # rad per straight tick
            graded = self.motors == "graded" or (self.motors == "mixed" and rng.random() < 0.5)
            wl = 1.0 + self.wheel_spread * rng.standard_normal(M)
            wr = 1.0 + self.wheel_spread * rng.standard_normal(M)
            if graded:  # each wheel's own drive (module doc)
                wl, wr = np.maximum(wl, MIN_FACTOR), np.maximum(wr, MIN_FACTOR)
                speed = speed * (wl + wr) / 2
                left, right = left * wl, right * wr
                curve = curve + (wl - wr) / 2 * cfg.omega_max_rad_s * w * cfg.tick_s
            d.update(speed=np.maximum(speed, MIN_FACTOR), turn_left=np.maximum(left, MIN_FACTOR),
                     turn_right=np.maximum(right, MIN_FACTOR), curve=curve)
        if self.msg_period is not None:
            d["msg_period"] = rng.integers(self.msg_period[0], self.msg_period[1] + 1, M + 1)
        if self.msg_success is not None:
            d["msg_loss"] = 1.0 - rng.uniform(*self.msg_success)
        if self.dist_noise_mm is not None:
            d["dist_noise_mm"] = rng.uniform(*self.dist_noise_mm)
        if self.wall_zone is not None:
            d["wall_zone_mm"] = cfg.wall_sense_mm * rng.uniform(*self.wall_zone, 4)
        if self.emitter_mobility is not None:
            d["emitter_mobility"] = rng.uniform(*self.emitter_mobility)
        if self.pivot_offset_mm is not None:
            d["pivot_mm"] = rng.uniform(*self.pivot_offset_mm, M)
        if cfg.lamps:  # last: worlds without lamps draw as before
            if self.lamp_brightness is not None:
                d["lamp_brightness"] = rng.uniform(*self.lamp_brightness)
            if self.lamp_shift_mm is not None:
                r, a = rng.uniform(*self.lamp_shift_mm), rng.uniform(-math.pi, math.pi)
                d["lamp_shift_mm"] = np.array([r * math.cos(a), r * math.sin(a)])
            if self.light_noise is not None:
                d["light_noise"] = rng.uniform(*self.light_noise)
        return d


_TABLE = Randomisation(speed=(0.7, 1.3), turn=(0.7, 1.3), speed_spread=0.1, turn_spread=0.1, curve_deg_s=2.0,
                       motors="mixed", wheel_spread=0.1, msg_period=(15, 17), msg_success=(0.6, 1.0),
                       dist_noise_mm=(0.0, 6.0), wall_zone=(0.5, 1.5), emitter_mobility=(0.0, 1.0),
                       pivot_offset_mm=(0.0, 16.5), lamp_brightness=(0.6, 1.4), lamp_shift_mm=(0.0, 50.0),
                       light_noise=(0.0, 30.0))

#: named randomisations for training: "none" is the nominal world; "table" spans the suite's variants;
#: :data:`~sim.compat.FREE_EMITTER_RANDOMISATION` is "table" with an emitter that collisions push like a robot in
#: every episode (an untaped Kilobot, the suite's hardest variant at 32 robots; "table" draws its mobility from 0-1)
RANDOMISATIONS: dict[str, Randomisation] = {
    "none": Randomisation(),
    "table": _TABLE,
    FREE_EMITTER_RANDOMISATION: dataclasses.replace(_TABLE, emitter_mobility=(1.0, 1.0)),
}


LAMP_SHIFT_MM = 50.0  #: the "lamp shifted" variant moves every lamp this far along +x
NOISIER_LIGHT = 30.0  #: the "noisier light sensor" variant adds this to the noise std (ADC counts)


def _lamps(lamps, peak: float = 1.0, shift: float = 0.0) -> str:
    """The lamps spec with every peak scaled (clipped to the ADC range) and every spot moved ``shift`` mm along +x."""
    from .light import ADC_MAX, format_lamps

    return format_lamps([dataclasses.replace(lp, peak=min(lp.peak * peak, ADC_MAX),
                                             x=lp.x + shift if lp.kind == "spot" else lp.x) for lp in lamps])


def robustness_suite(cfg: WorldConfig) -> dict[str, tuple[WorldConfig, Randomisation | None]]:
    """Named variants of ``cfg`` (tick-level worlds): ``{name: (world, randomisation or None)}``,
    "nominal" first. Variants of one global constant are plain configs; per-robot spreads, graded
    motors and uneven light are randomisations (drawn per env and reset)."""
    if not cfg.tick_level or cfg.msg_period_ticks < 1:
        raise ValueError(f"the robustness suite models a Kilobot table: use a tick-level world, not '{cfg.name}'")
    r = dataclasses.replace
    suite: dict[str, tuple[WorldConfig, Randomisation | None]] = {"nominal": (cfg, None)}
    for f in (0.7, 1.3):
        suite[f"speed {f - 1:+.0%}"] = (r(cfg, v_max_mm_s=cfg.v_max_mm_s * f), None)
    for f in (0.7, 1.3):
        suite[f"turn rate {f - 1:+.0%}"] = (r(cfg, omega_max_rad_s=cfg.omega_max_rad_s * f), None)
    suite["calibration spread"] = (cfg, Randomisation(speed_spread=0.1, turn_spread=0.1, curve_deg_s=2.0))
    suite["graded motors"] = (cfg, Randomisation(motors="graded", wheel_spread=0.1))
    for T in (15, 17):
        suite[f"msg period {T}"] = (r(cfg, msg_period_ticks=T), None)
    for ok in (0.6, 1.0):
        suite[f"msg success {ok:.1f}"] = (r(cfg, msg_loss=round(1.0 - ok, 6)), None)
    for sd in (0.0, 6.0):
        suite[f"dist noise {sd:g} mm"] = (r(cfg, dist_noise_mm=sd), None)
    if cfg.light_wall != cfg.light_floor:  # lit walls (unlit ones, e.g. phototaxis's, have no wall zone to vary)
        suite["dim light"] = (r(cfg, wall_sense_mm=cfg.wall_sense_mm * 0.5), None)
        suite["bright light"] = (r(cfg, wall_sense_mm=cfg.wall_sense_mm * 1.5), None)
        suite["uneven light"] = (cfg, Randomisation(wall_zone=(0.5, 1.5)))
    if cfg.lamps:  # lamps (sim.light): dimmer, brighter, moved, and a noisier sensor
        lamps = cfg.lamp_list
        suite["lamps dimmer"] = (r(cfg, lamps=_lamps(lamps, peak=0.6)), None)
        suite["lamps brighter"] = (r(cfg, lamps=_lamps(lamps, peak=1.4)), None)
        suite["lamp shifted"] = (r(cfg, lamps=_lamps(lamps, shift=LAMP_SHIFT_MM)), None)
        suite["noisier light sensor"] = (r(cfg, light_noise=cfg.light_noise + NOISIER_LIGHT), None)
    if cfg.pivot_offset_mm > 0:
        suite["centre pivot"] = (r(cfg, pivot_offset_mm=0.0), None)
    else:
        suite["leg pivot"] = (r(cfg, pivot_offset_mm=LEG_PIVOT_MM), None)
    if cfg.collisions and cfg.emitter:  # a world without an emitter has none to tape or free
        suite[EMITTER_FIXED_VARIANT if cfg.emitter_mobility > 0 else EMITTER_PUSHED_VARIANT] = (
            r(cfg, emitter_mobility=0.0 if cfg.emitter_mobility > 0 else 1.0), None)
    return suite
