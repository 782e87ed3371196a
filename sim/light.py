"""The light field over the table and what each robot's ambient-light sensor reads.

Kilobot facts used (``../shared/reference/kilobot-platform.md``): a Kilobot has one ambient-light
sensor on top, read by the 10-bit ADC: ``int16_t get_ambientlight(void)`` returns 0..1023, and -1
while a message is being received (the controller retries or keeps its last value); a message
arriving during a reading can spoil the reading, so controllers tolerate outliers. Everything else
here (lamp shapes, noise, per-robot gain and offset) is a model assumption, sized in the worlds
that use it.

The field (ADC counts, float) at a robot's centre is the table's base light, today's lit walls
(``light_wall`` within ``wall_sense_mm`` of a wall, else ``light_floor``: :func:`sim.radio.light_readings`),
plus each lamp of ``WorldConfig.lamps``:

``spot:x,y,radius,edge,peak``
    a lamp above the table lighting a disc: ``peak`` counts up to ``radius - edge/2`` mm from
    ``(x, y)``, 0 beyond ``radius + edge/2``, linear in between (a soft edge; half the peak at
    ``radius``, the spot's nominal radius). ``edge = 0`` is a hard edge (peak at ``d <= radius``).
``side:angle_deg,peak``
    a lamp at one side of the table, in direction ``angle_deg`` from the centre (0 = the +x wall):
    a linear gradient, ``peak`` at that wall's centre line, 0 at the opposite wall. A heavy body
    (``WorldConfig.body_radius_mm``) casts a shadow in its light: behind the body, within its radius of
    the line from the lamp through its centre, :data:`BODY_SHADE` of the lamp's light is missing.

Lamps are separated by ``;``. A reading is ``clip(rint(field · gain + offset + noise), 0, 1023)``
with a per-robot ``gain = 1 + light_gain_spread · N(0, 1)`` (at least :data:`MIN_GAIN`) and
``offset = light_offset_spread · N(0, 1)`` drawn per episode from the env's light stream (robots
differ), and ``noise = light_noise · N(0, 1)`` per reading; then -1 with probability
``light_dropout`` (receiving). A world without lamps, noise or spreads reads exactly the lit-wall
values of before (no rounding, no extra random draws).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kiloforge.errors import InputError

ADC_MAX = 1023  #: get_ambientlight() is a 10-bit ADC conversion: 0..1023 (platform notes)
MIN_GAIN = 0.1  #: per-robot sensor gains are clipped to at least this
LAMP_KINDS = {"spot": ("x", "y", "radius", "edge", "peak"), "side": ("angle_deg", "peak")}
MAX_LAMPS = 8
#: the share of a side lamp's light a heavy body (:mod:`sim.body`) keeps from the floor behind it (an assumption:
#: the rest reaches it scattered)
BODY_SHADE = 0.9


@dataclass(frozen=True)
class Lamp:
    """One lamp of ``WorldConfig.lamps`` (see the module doc); unused fields are 0."""

    kind: str
    x: float = 0.0
    y: float = 0.0
    radius: float = 0.0
    edge: float = 0.0
    angle_deg: float = 0.0
    peak: float = 0.0

    def spec(self) -> str:
        return f"{self.kind}:" + ",".join(f"{getattr(self, k):g}" for k in LAMP_KINDS[self.kind])


def parse_lamps(spec: str, where: str) -> tuple[Lamp, ...]:
    """The lamps of ``spec`` (``kind:v,v,...;...``), checked; InputError naming ``where`` otherwise."""
    if not spec:
        return ()
    out = []
    for part in spec.split(";"):
        kind, _, vals = part.partition(":")
        if kind not in LAMP_KINDS:
            raise InputError(f"{where}: unknown lamp kind {kind!r} in {spec!r}; choose from: "
                             + ", ".join(f"{k}:{','.join(v)}" for k, v in LAMP_KINDS.items()))
        names = LAMP_KINDS[kind]
        try:
            nums = [float(v) for v in vals.split(",")]
        except ValueError:
            nums = []
        if len(nums) != len(names) or not all(math.isfinite(v) for v in nums):
            raise InputError(f"{where}: lamp {part!r} needs {len(names)} finite numbers: {kind}:{','.join(names)}")
        lamp = Lamp(kind, **dict(zip(names, nums)))
        if lamp.radius < 0 or lamp.edge < 0 or not 0 <= lamp.peak <= ADC_MAX:
            raise InputError(f"{where}: lamp {part!r}: radius and edge must be >= 0, peak in 0..{ADC_MAX}")
        out.append(lamp)
    if len(out) > MAX_LAMPS:
        raise InputError(f"{where}: at most {MAX_LAMPS} lamps, got {len(out)}")
    return tuple(out)


def format_lamps(lamps: Sequence[Lamp]) -> str:
    return ";".join(lamp.spec() for lamp in lamps)


def spot_profile(d_mm: np.ndarray, radius: float, edge: float) -> np.ndarray:
    """A spot's relative intensity in [0, 1] at centre distance ``d_mm`` (1 inside, linear soft edge)."""
    if edge <= 0:
        return (d_mm <= radius).astype(np.float64)
    return np.clip((radius + 0.5 * edge - d_mm) / edge, 0.0, 1.0)


def in_shadow(pos: np.ndarray, body: np.ndarray, radius: float, angle_deg: float) -> np.ndarray:
    """(B, M) True where ``pos`` (B, M, 2) lies in the shadow a disc of ``radius`` at ``body`` (B, 2) casts in the
    parallel light of a side lamp in direction ``angle_deg``: behind the disc's centre, less than ``radius`` off
    the line through it."""
    a = math.radians(angle_deg)
    rel = pos - body[:, None, :]
    along = rel[..., 0] * math.cos(a) + rel[..., 1] * math.sin(a)
    across = rel[..., 1] * math.cos(a) - rel[..., 0] * math.sin(a)
    return (along < 0) & (np.abs(across) < radius)


def lamp_field(pos: np.ndarray, lamps: Sequence[Lamp], arena_half_mm: float, brightness: np.ndarray | None = None,
               shift_mm: np.ndarray | None = None, body: np.ndarray | None = None,
               body_radius: float = 0.0) -> np.ndarray:
    """(B, M) float64 sum of the lamps' light at ``pos`` (B, M, 2): ``brightness`` (B,) factors on every
    peak, ``shift_mm`` (B, 2) moves every lamp (per env; None: nominal); ``body`` (B, 2): a heavy body of
    ``body_radius`` there shades :data:`BODY_SHADE` of each side lamp's light behind it (:func:`in_shadow`)."""
    B, M = pos.shape[:2]
    p = pos if shift_mm is None else pos - shift_mm[:, None, :]
    out = np.zeros((B, M))
    for lamp in lamps:
        if lamp.kind == "spot":
            d = np.hypot(p[..., 0] - lamp.x, p[..., 1] - lamp.y)
            out += lamp.peak * spot_profile(d, lamp.radius, lamp.edge)
        else:
            a = math.radians(lamp.angle_deg)
            t = (p[..., 0] * math.cos(a) + p[..., 1] * math.sin(a)) / arena_half_mm  # -1 far wall .. 1 lamp's wall
            side = lamp.peak * np.clip(0.5 * (1.0 + t), 0.0, 1.0)
            if body is not None:
                side = np.where(in_shadow(pos, body, body_radius, lamp.angle_deg), (1.0 - BODY_SHADE) * side, side)
            out += side
    return out if brightness is None else out * brightness[:, None]


@dataclass
class SensorDraw:
    """Per-robot sensor gain and offset of one episode, (B, M) each (drawn by :func:`draw_sensors`)."""

    gain: np.ndarray
    offset: np.ndarray


def draw_sensors(cfg, n_robots: int, rngs: Sequence[np.random.Generator]) -> SensorDraw | None:
    """Each env's per-robot gains, then offsets, from its light stream (None: the world has no spread)."""
    if cfg.light_gain_spread == 0 and cfg.light_offset_spread == 0:
        return None
    g = np.stack([rng.standard_normal((2, n_robots)) for rng in rngs])  # (B, 2, M)
    return SensorDraw(np.maximum(1.0 + cfg.light_gain_spread * g[:, 0], MIN_GAIN), cfg.light_offset_spread * g[:, 1])


def sensor_readings(base: np.ndarray, pos: np.ndarray, cfg, lamps: Sequence[Lamp], rngs: Sequence[np.random.Generator],
                    sensors: SensorDraw | None, brightness: np.ndarray | None = None,
                    shift_mm: np.ndarray | None = None, noise: np.ndarray | None = None,
                    body: np.ndarray | None = None) -> np.ndarray:
    """(B, M) int16 readings before dropout: ``base`` (B, M) plus the lamps, gain, offset, noise (``noise``
    (B,) std per env, else ``cfg.light_noise``), rounded and clipped to the ADC's range; ``body`` (B, 2) the
    heavy body's centre, whose shadow darkens the side lamps (None: no body)."""
    v = base + lamp_field(pos, lamps, cfg.arena_half_mm, brightness, shift_mm, body, cfg.body_radius_mm)
    if sensors is not None:
        v = v * sensors.gain + sensors.offset
    sd = cfg.light_noise if noise is None else noise[:, None]
    if np.any(np.asarray(sd) > 0):
        M = pos.shape[1]
        v = v + sd * np.stack([rng.standard_normal(M) for rng in rngs])
    return np.clip(np.rint(v), 0, ADC_MAX).astype(np.int16)
