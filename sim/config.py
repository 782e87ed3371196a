"""World configuration: every constant of the simulated world, in one frozen dataclass.

Units inside kiloforge are millimetres, seconds and radians. A :class:`WorldConfig` travels with
every policy artifact, and the exporter takes every sensing constant (communication radius, RBF
centres and width, normalisers, wall-light threshold, control period, motor schedule) from it, so a
policy can never be rendered with a world other than the one it was trained in.

Two presets:

``thesis``
    The world of the thesis (§4.1–4.3), converted with 1 unit = 1 cm = 10 mm: arena ±100 mm,
    communication radius 40 mm, 11 RBF centres equally spaced over [0, 40] mm with σ = 2.5 mm,
    10 mm/s, 45 deg/s, ΔT = 1 s, point robots without collisions and a fixed target, 200-step
    episodes, the reward of §4.2. Messages: every robot within the radius is heard exactly once per control period, with
    the exact (float) distance, no loss.

``kilobot``
    What real Kilobots see (``../shared/reference/kilobot-platform.md``): 33 mm discs that cannot
    overlap, distances as ``estimate_distance`` reports them (integer mm, ≥ 33, ≤ 255), an IR range
    of 85 mm (platform notes: 70–100 mm, surface dependent), one message per robot every 16
    kilo_ticks (≈1.9/s) with a random phase and loss, Gaussian distance noise, a control period of
    31 kilo_ticks (30.52 Hz ⇒ 1.016 s), motion by the straight / pivot motor schedule of
    :mod:`sim.motion`, and a 500 × 500 mm arena (a common Kilobot table size; 5.9 communication
    radii wide, close to the thesis's 5 radii).

    A pivot turns the robot about a leg, not its centre (platform notes: "pivots about a leg with
    one motor"). A Kilobot stands on three legs, one ahead and two behind at ±125.5° from the
    heading (Kilombo's ``leg_angle``, docs/kilombo.md); with one motor running, the rear leg on the
    side of the motor that is off, on the inside of the turn, stays put and the body swings about
    it. So a left (counter-clockwise) pivot turns about the point ``pivot_offset_mm`` = 16.5 mm
    (the rim of the body; Kilombo: its 17 mm radius) from the centre at heading + 125.5°, a right
    pivot about the one at heading - 125.5°, and the centre moves along an arc around it, ≈13 mm/s
    forwards and towards the turn (direction heading ± 35.5°). ``pivot_offset_mm = 0`` pivots
    about the centre.

    A task's emitter (a robot that only transmits and has a role, :attr:`WorldConfig.emitter`) is
    taped down (``emitter_mobility = 0``): the tasks' benchmarks (and localisation's packing ceiling)
    assume a stationary one, and the flashing instructions tell users to tape it to the table.
    Untaped, the robots push it (an independent Kilobot simulator running our firmware saw it pushed
    146 mm on average per 300 s run); that world is a robustness variant (``emitter_mobility = 1``,
    :mod:`sim.variants`) and part of the "table" domain randomisation.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kiloforge import numfmt
from kiloforge.errors import InputError
from kiloforge.validate import check_keys, check_str, check_typed, show

from .compat import world_from_file, world_to_file
from .features import LEGACY_FEATURES, feature, parse_features
from .light import parse_lamps

# Localisation's observation layout (docs/design.md control-step contract, step 2; thesis §4.1), the
# legacy default of WorldConfig.obs_features. Code that reads observations of any world uses
# WorldConfig.obs_index(name) (sim/features.py holds the features).
OBS_WALL = 0  #: 1.0 when the ambient-light reading says a wall is near, else 0.0
OBS_TARGET = 1  #: distance to the target / comm radius in [0, 1] when heard this period, else -1
OBS_NBR_SENSING = 2  #: 1.0 when a heard searcher's latest message says it senses the target
OBS_RBF = 3  #: first of the ``n_rbf`` histogram bins
ACTION_DIM = 2  #: (u_left, u_right), each in [0, 1]

ROLE_SEARCHER = 0
ROLE_TARGET = 1

KILO_TICK_HZ = 30.52  #: kilo_ticks per second, measured (platform notes: 305 ticks in 10 s)
MAX_ARENA_HALF_MM = 100_000.0  #: a 200 m arena; larger ones only serve to exhaust memory
MAX_EPISODE_STEPS = 1_000_000  #: control periods per episode (about 11 days of Kilobot time)
#: control periods per episode a command runs when the length comes from a file's world rather than a flag
#: (a policy file must not decide how long a command works: :func:`run_steps`)
FILE_STEPS_CAP = 10_000
#: and, in a tick-level world (whose work per period grows with period_ticks), kilo_ticks per episode:
#: 10,000 periods of the kilobot preset's 31 ticks
FILE_TICKS_CAP = 310_000
MAX_ROBOTS = 1024  #: robots per simulated swarm, in every command (--robots) and config
#: RBF width and normaliser: outside these the features (exp(-(d - c)^2 / 2 sigma^2) / norm) underflow to 0 / 0 or
#: overflow; inside them every feature is finite and the firmware's table can be computed
RBF_SIGMA_RANGE_MM = (1e-3, 1e4)
RBF_NORM_RANGE = (1e-3, 1e6)
MAX_RBF_CENTRE_MM = 1000.0  #: distances are reported in whole mm up to 255: a centre beyond this is never reached
#: control periods of an evaluation episode in the thesis's benchmark (500 episodes x 500 steps), used
#: where policies are compared (learn evaluate, sweeps, ES evaluation); sim and export verify run the
#: world's own episode (WorldConfig.episode_steps: thesis 200, kilobot 300), as the policy was trained
BENCHMARK_STEPS = 500
BENCHMARK_EPISODES = 500  #: episodes per policy and swarm size in that benchmark
#: the episode seed of the held-out evaluations in docs/results/localisation.md: no training or model selection draws from it
HELD_OUT_SEED = 20261202
VALIDATION_SEED = 777  #: episode seed of tuning and model selection (the hand-written rules, choosing a run to ship)


@dataclass(frozen=True)
class WorldConfig:
    """The simulated world. Frozen: derive variants with :func:`dataclasses.replace`."""

    name: str = "thesis"  #: preset name (free text, shown in plots and manifests)
    # --- arena and bodies -------------------------------------------------------------------
    arena_half_mm: float = 100.0  #: the arena is the square [-a, a]²; robot centres stay inside
    robot_radius_mm: float = 0.0  #: 0 = point robots (thesis); 16.5 = Kilobot discs
    collisions: bool = False  #: True: discs never overlap (pushed apart after every move)
    #: how collisions move the emitter's disc, relative to a robot's: 0 = fixed (taped down; a robot
    #: touching it takes the whole push), 1 = pushed like any robot (a Kilobot standing on the table).
    #: Collision worlds only; the task follows the emitter's position
    emitter_mobility: float = 0.0
    #: the emitter's body: 0 = a robot's disc (above); > 0 = the emitter rides on a heavy disc of this radius that
    #: robots push together (:mod:`sim.body`: it moves only when their summed push exceeds ``body_friction``)
    body_radius_mm: float = 0.0
    #: the heavy body's static friction in full robot pushes: the summed push must exceed this to move it
    #: (k robots pushing the same way move it, k - 1 do not, for k - 1 < body_friction < k)
    body_friction: float = 0.0
    # --- motion -----------------------------------------------------------------------------
    #: tick-level worlds: a pivot turns the robot about a point this far from its centre (a leg;
    #: 0 = about the centre). Its centre then moves along an arc around that point
    pivot_offset_mm: float = 0.0
    #: bearing of the pivot point from the heading, on the side of the turn: a left (counter-
    #: clockwise) pivot turns about the point at heading + angle, a right pivot at heading - angle
    pivot_angle_deg: float = 125.5
    v_max_mm_s: float = 10.0  #: straight speed at k_linear = 1 (thesis v_linear,max = 1 cm/s)
    omega_max_rad_s: float = math.pi / 4  #: turn rate at |k_angular| = 1 (thesis 45 deg/s)
    control_period_s: float = 1.0  #: ΔT; for tick-level worlds period_ticks / KILO_TICK_HZ
    tick_level: bool = False  #: False: thesis kinematics once per period; True: motor schedule per tick
    period_ticks: int = 31  #: control period in kilo_ticks (firmware rate limit; tick-level motion)
    # --- radio ------------------------------------------------------------------------------
    comm_radius_mm: float = 40.0  #: messages are received when centres are at most this far apart
    msg_period_ticks: int = 0  #: 0: every robot is heard once per period (thesis); else tx interval
    msg_loss: float = 0.0  #: probability that one message is lost at one receiver
    dist_noise_mm: float = 0.0  #: std of Gaussian noise on measured distance
    dist_integer: bool = False  #: True: measured distances are rounded to integer mm (estimate_distance)
    dist_min_mm: float = 0.0  #: measured distances are clipped to [dist_min_mm, dist_max_mm]
    dist_max_mm: float = 255.0
    neighbour_table_size: int = 16  #: firmware neighbour-table capacity (searchers per period)
    emitter_uid: int = 0  #: kilo_uid of the emitter; robot i has kilo_uid i + 1
    # --- sensing ----------------------------------------------------------------------------
    n_rbf: int = 11  #: number of RBF bins in the distance histogram
    rbf_lo_mm: float = 0.0  #: first RBF centre
    rbf_hi_mm: float = 40.0  #: last RBF centre (centres equally spaced)
    rbf_sigma_mm: float = 2.5  #: RBF width σ
    rbf_norm: float = 4.0  #: histogram bins are divided by this (≈ the most neighbours per bin)
    wall_sense_mm: float = 10.0  #: the light reading is high when a wall is at most this far
    light_floor: int = 200  #: ambient-light reading away from walls (10-bit ADC counts)
    light_wall: int = 800  #: ambient-light reading near a wall (walls are lit)
    light_threshold: int = 500  #: firmware: wall flag = reading >= threshold
    light_dropout: float = 0.0  #: probability a reading is -1 (busy receiving); firmware keeps the last flag
    #: lamps over the table (:mod:`sim.light`: ``spot:x,y,radius,edge,peak``, ``side:angle_deg,peak``, ``;``-separated),
    #: added to the floor / lit-wall light; "" = none
    lamps: str = ""
    light_noise: float = 0.0  #: std of the sensor noise per reading (ADC counts)
    light_gain_spread: float = 0.0  #: per-robot relative std of the sensor gain (drawn per episode)
    light_offset_spread: float = 0.0  #: per-robot std of the sensor offset (ADC counts, drawn per episode)
    # --- task -------------------------------------------------------------------------------
    episode_steps: int = 200  #: control periods per episode
    reward_scale: float = 5.0  #: thesis §4.2 factor 5
    action_penalty: float = 0.01  #: thesis §4.2 weight of the squared action norm
    spawn_margin_mm: float = 0.0  #: robots and the emitter spawn this far inside the walls
    #: True: an emitter (kilo_uid ``emitter_uid``), a robot that only transmits, stands in the world, and the
    #: firmware has its role; set by the task (:meth:`sim.tasks.Task.world`)
    emitter: bool = True
    #: the observation, comma-separated feature names of :mod:`sim.features` in input order; set by the task
    obs_features: str = LEGACY_FEATURES

    def __post_init__(self) -> None:
        check_str(self.name, "WorldConfig name", max_len=64)
        for f in dataclasses.fields(self):  # exact types first: 11.0 is not an int, "true" not a bool
            value = getattr(self, f.name)
            typed = check_typed(value, f.type, f"WorldConfig '{self.name}': {f.name}")
            if typed is not value:
                object.__setattr__(self, f.name, typed)

        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise InputError(f"WorldConfig '{self.name}': {msg}")

        need(0 < self.arena_half_mm <= MAX_ARENA_HALF_MM,
             f"arena_half_mm must be in (0, {MAX_ARENA_HALF_MM}], got {self.arena_half_mm}")
        need(self.robot_radius_mm >= 0, f"robot_radius_mm must be >= 0, got {self.robot_radius_mm}")
        need(0.0 <= self.emitter_mobility <= 1.0, f"emitter_mobility must be in [0, 1], got {self.emitter_mobility}")
        need(self.pivot_offset_mm >= 0, f"pivot_offset_mm must be >= 0, got {self.pivot_offset_mm}")
        need(0 <= self.body_radius_mm < self.arena_half_mm,
             f"body_radius_mm must be in [0, arena_half_mm), got {self.body_radius_mm}")
        need(0 <= self.body_friction <= 1e3, f"body_friction must be in [0, 1000], got {self.body_friction}")
        need(self.body_radius_mm == 0 or (self.emitter and self.collisions and self.robot_radius_mm > 0),
             "body_radius_mm > 0 needs an emitter and a collision world (robots push the body)")
        need(0.0 <= self.pivot_angle_deg <= 180.0, f"pivot_angle_deg must be in [0, 180], got {self.pivot_angle_deg}")
        need(self.pivot_offset_mm == 0 or self.tick_level,
             "pivot_offset_mm > 0 needs a tick-level world (the thesis kinematics turn about the centre)")
        need(self.spawn_margin_mm >= 0 and self.spawn_margin_mm < self.arena_half_mm,
             f"spawn_margin_mm must be in [0, arena_half_mm), got {self.spawn_margin_mm}")
        need(self.v_max_mm_s >= 0, f"v_max_mm_s must be >= 0, got {self.v_max_mm_s}")
        need(self.omega_max_rad_s >= 0, f"omega_max_rad_s must be >= 0, got {self.omega_max_rad_s}")
        need(self.control_period_s > 0, f"control_period_s must be > 0, got {self.control_period_s}")
        need(1 <= self.period_ticks <= 255, f"period_ticks must be in 1..255, got {self.period_ticks}")
        need(self.comm_radius_mm > 0, f"comm_radius_mm must be > 0, got {self.comm_radius_mm}")
        need(self.comm_radius_mm <= 255, f"comm_radius_mm must be <= 255 (uint8 mm), got {self.comm_radius_mm}")
        need(0 <= self.msg_period_ticks <= 0xFFFF, f"msg_period_ticks must be in 0..65535, got {self.msg_period_ticks}")
        need(0.0 <= self.msg_loss < 1.0, f"msg_loss must be in [0, 1), got {self.msg_loss}")
        need(self.dist_noise_mm >= 0, f"dist_noise_mm must be >= 0, got {self.dist_noise_mm}")
        need(0 <= self.dist_min_mm <= self.dist_max_mm <= 255,
             f"need 0 <= dist_min_mm <= dist_max_mm <= 255, got {self.dist_min_mm}, {self.dist_max_mm}")
        need(1 <= self.neighbour_table_size <= 64,
             f"neighbour_table_size must be in 1..64, got {self.neighbour_table_size}")
        need(0 <= self.emitter_uid <= 0xFFFF, f"emitter_uid must be a uint16, got {self.emitter_uid}")
        need(1 <= self.n_rbf <= 32, f"n_rbf must be in 1..32, got {self.n_rbf}")
        need(self.rbf_hi_mm >= self.rbf_lo_mm >= 0, "need 0 <= rbf_lo_mm <= rbf_hi_mm")
        need(self.rbf_hi_mm <= MAX_RBF_CENTRE_MM, f"rbf_hi_mm must be <= {MAX_RBF_CENTRE_MM:g}, got {self.rbf_hi_mm}")
        lo, hi = RBF_SIGMA_RANGE_MM
        need(lo <= self.rbf_sigma_mm <= hi, f"rbf_sigma_mm must be in [{lo:g}, {hi:g}], got {self.rbf_sigma_mm}")
        lo, hi = RBF_NORM_RANGE
        need(lo <= self.rbf_norm <= hi, f"rbf_norm must be in [{lo:g}, {hi:g}], got {self.rbf_norm}")
        # the firmware's RBF table at the finest input resolution must see something: an all-zero table
        # would give the robot no neighbour histogram while the float policy has one
        table = numfmt.rbf_table(self.rbf_centres_mm, self.rbf_sigma_mm, self.rbf_norm, self.comm_radius_mm,
                                 numfmt.DEFAULT_INPUT_EXP)
        need(bool(table.any()), f"the RBF features (centres {self.rbf_lo_mm:g}..{self.rbf_hi_mm:g} mm, "
             f"rbf_sigma_mm {self.rbf_sigma_mm:g}, rbf_norm {self.rbf_norm:g}) are below "
             f"1/{2 << numfmt.DEFAULT_INPUT_EXP} at every distance up to comm_radius_mm {self.comm_radius_mm:g}: "
             "the firmware's RBF table would be all zero (lower rbf_norm or move the centres within the radius)")
        need(0 <= self.light_floor <= 1023 and 0 <= self.light_wall <= 1023
             and 0 <= self.light_threshold <= 1023, "light readings and threshold must be in 0..1023")
        need(0.0 <= self.light_dropout < 1.0, f"light_dropout must be in [0, 1), got {self.light_dropout}")
        for k in ("light_noise", "light_gain_spread", "light_offset_spread"):
            need(0.0 <= getattr(self, k) <= 1e4, f"{k} must be in [0, 1e4], got {getattr(self, k)}")
        check_str(self.lamps, f"WorldConfig '{self.name}': lamps", max_len=512)
        object.__setattr__(self, "_lamps", parse_lamps(self.lamps, f"WorldConfig '{self.name}'"))
        need(1 <= self.episode_steps <= MAX_EPISODE_STEPS,
             f"episode_steps must be in 1..{MAX_EPISODE_STEPS}, got {self.episode_steps}")
        if self.tick_level:
            need(self.msg_period_ticks >= 1, "tick-level worlds need msg_period_ticks >= 1")
        check_str(self.obs_features, f"WorldConfig '{self.name}': obs_features", max_len=256)
        features = parse_features(self.obs_features, self.emitter, f"WorldConfig '{self.name}'")
        slices, i = {}, 0
        for n in features:  # the layout once: the simulator reads it every step
            w = feature(n).width(self)
            slices[n] = slice(i, i + w)
            i += w
        object.__setattr__(self, "_features", features)
        object.__setattr__(self, "_table_features", tuple(n for n in features if feature(n).table is not None))
        object.__setattr__(self, "_obs_slices", slices)
        object.__setattr__(self, "_obs_dim", i)

    # --- derived constants (one definition each) --------------------------------------------
    @property
    def features(self) -> tuple[str, ...]:
        """The observation's feature names in input order (``obs_features``, parsed)."""
        return self._features  # type: ignore[attr-defined]

    @property
    def table_features(self) -> tuple[str, ...]:
        """The features among them that a task brought (:mod:`sim.table_features`), in input order."""
        return self._table_features  # type: ignore[attr-defined]

    @property
    def lamp_list(self) -> tuple:
        """The lamps of ``lamps``, parsed (:class:`sim.light.Lamp`)."""
        return self._lamps  # type: ignore[attr-defined]

    @property
    def graded_light(self) -> bool:
        """True when readings go beyond the lit-wall values: lamps, sensor noise or per-robot spreads."""
        return bool(self.lamps) or self.light_noise > 0 or self.light_gain_spread > 0 or self.light_offset_spread > 0

    def has_feature(self, name: str) -> bool:
        return name in self._obs_slices  # type: ignore[attr-defined]

    def obs_index(self, name: str) -> int:
        """First input of feature ``name`` in this world's observation (KeyError naming the layout when absent)."""
        return self.obs_slice(name).start

    def obs_slice(self, name: str) -> slice:
        """The inputs of feature ``name`` (KeyError naming the layout when absent)."""
        try:
            return self._obs_slices[name]  # type: ignore[attr-defined]
        except KeyError:
            raise KeyError(f"world '{self.name}' observes {self.obs_features}, not {name!r}") from None

    @property
    def obs_dim(self) -> int:
        """Length of one observation: the sum of its features' widths (localisation: 3 + n_rbf)."""
        return self._obs_dim  # type: ignore[attr-defined]

    @property
    def has_roles(self) -> bool:
        """True when a robot of the task's transmits with a role (the emitter): the firmware gets the role
        bit, the table of the kilo_uids that take the role and the role's program."""
        return bool(self.emitter)

    @property
    def tuple_dim(self) -> int:
        """Length of one history tuple (previous action, observation)."""
        return ACTION_DIM + self.obs_dim

    def history_dim(self, t_prev: int) -> int:
        """Actor input width for a history of ``t_prev`` tuples (oldest first)."""
        return t_prev * self.tuple_dim

    @property
    def rbf_centres_mm(self) -> np.ndarray:
        """RBF centres μ_k, shape (n_rbf,)."""
        return np.linspace(self.rbf_lo_mm, self.rbf_hi_mm, self.n_rbf)

    @property
    def tick_s(self) -> float:
        """Length of one kilo_tick in seconds."""
        return 1.0 / KILO_TICK_HZ

    @property
    def state_dim_per_robot(self) -> int:
        return 3

    def state_dim(self, n_robots: int) -> int:
        """Critic state width: the emitter's (x, y) and every robot's (x, y, φ), all normalised."""
        return 2 + 3 * n_robots

    @property
    def state_scale(self) -> tuple[float, float]:
        """Normalisers of the critic state: positions / arena_half_mm, headings / π."""
        return (self.arena_half_mm, math.pi)

    # --- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """All fields under their world-JSON keys (:data:`sim.compat.WORLD_KEYS`), except later additions at the
        value that reproduces the older world (so the worlds, and hashes, of artifacts written before a field
        existed stay the same)."""
        d = dataclasses.asdict(self)
        for k, legacy in _LATER_FIELDS.items():
            if d[k] == legacy:
                del d[k]
        return world_to_file(d)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "WorldConfig":
        """Build from a dict (e.g. policy metadata) whose keys are field names or their world-JSON keys
        (:data:`sim.compat.WORLD_KEYS`); missing fields take the defaults, unknown keys and values of the wrong
        type or range are an :class:`~kiloforge.errors.InputError` naming them."""
        if not isinstance(d, dict):
            raise InputError(f"world config must be a JSON object, got {show(d)}")
        d = world_from_file(d, "world config")
        check_keys(d, "world config", frozenset(f.name for f in dataclasses.fields(cls)))
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)


#: fields added after policy artifacts were first written, and the value that older worlds had
_LATER_FIELDS: dict[str, Any] = {"emitter_mobility": 0.0, "pivot_offset_mm": 0.0, "pivot_angle_deg": 125.5,
                                 "emitter": True, "obs_features": LEGACY_FEATURES, "lamps": "", "light_noise": 0.0,
                                 "light_gain_spread": 0.0, "light_offset_spread": 0.0, "body_radius_mm": 0.0,
                                 "body_friction": 0.0}

THESIS = WorldConfig()

KILOBOT = WorldConfig(
    name="kilobot",
    arena_half_mm=250.0,
    robot_radius_mm=16.5,  # 33 mm body (platform notes)
    collisions=True,
    emitter_mobility=0.0,  # taped down: the benchmarks' stationary emitter (see the module doc)
    v_max_mm_s=10.0,  # ≈1 cm/s (platform notes)
    omega_max_rad_s=math.pi / 4,  # ≈45 deg/s pivot (platform notes)
    pivot_offset_mm=16.5,  # about a leg at the rim (platform notes; Kilombo: its 17 mm radius)
    pivot_angle_deg=125.5,  # the rear legs' bearing from the heading (Kilombo's leg_angle)
    control_period_s=31 / KILO_TICK_HZ,
    tick_level=True,
    period_ticks=31,  # ≈1.016 s at 30.52 Hz
    comm_radius_mm=85.0,  # IR range 70–100 mm, surface dependent (platform notes)
    msg_period_ticks=16,  # kilolib asks for a message every ~16 ticks (0.524 s, ≈1.9/s)
    msg_loss=0.15,  # assumption: collisions + floor reflections; tune to your surface
    dist_noise_mm=3.0,  # assumption: estimate_distance scatter after calibration
    dist_integer=True,  # estimate_distance returns uint8 mm
    dist_min_mm=33.0,  # touching discs (platform notes)
    dist_max_mm=255.0,  # estimate_distance clips at 255
    neighbour_table_size=16,
    n_rbf=11,
    rbf_lo_mm=33.0,  # no distance below 33 mm is ever reported
    rbf_hi_mm=85.0,
    rbf_sigma_mm=3.25,  # same σ / spacing ratio as the thesis (2.5 / 4)
    rbf_norm=4.0,
    wall_sense_mm=40.0,
    light_dropout=0.02,  # get_ambientlight() returns -1 while a message is being received
    episode_steps=300,
    spawn_margin_mm=16.5,
)

PRESETS: dict[str, WorldConfig] = {"thesis": THESIS, "kilobot": KILOBOT}
#: the world of every command without ``--world`` (sim, learn train / train-recurrent / train-es): the robots'.
#: ``--world thesis`` is the thesis's (the thesis reproduction, tests/bench/reproduce_thesis.py, names it)
DEFAULT_WORLD = KILOBOT.name


def preset(name: str, **overrides: Any) -> WorldConfig:
    """Return the named preset, optionally with fields replaced.

    >>> preset("thesis").comm_radius_mm
    40.0
    >>> preset("kilobot", msg_loss=0.0).msg_loss
    0.0
    """
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"unknown preset '{name}'; choose one of: {', '.join(sorted(PRESETS))}")
    cfg = PRESETS[name]
    return dataclasses.replace(cfg, **overrides) if overrides else cfg


def run_steps(world: WorldConfig, steps: int | None, flag: str) -> int:
    """Control periods per episode a command runs: ``steps`` when the user gave ``flag``, else the world's
    ``episode_steps``, which a policy file sets: refused above :data:`FILE_STEPS_CAP` periods or, in a
    tick-level world, :data:`FILE_TICKS_CAP` kilo_ticks (InputError naming the cap and the flag that runs longer)."""
    if steps is not None:
        return int(steps)
    hint = f"pass {flag} N (up to {MAX_EPISODE_STEPS:,}) to choose the length"
    if world.episode_steps > FILE_STEPS_CAP:
        raise InputError(f"the policy's world '{world.name}' sets episode_steps {world.episode_steps:,}, more than the "
                         f"{FILE_STEPS_CAP:,} control periods a command runs by default; {hint}")
    ticks = world.episode_steps * world.period_ticks
    if world.tick_level and ticks > FILE_TICKS_CAP:
        raise InputError(f"the policy's world '{world.name}' sets episodes of {world.episode_steps:,} periods x "
                         f"{world.period_ticks} kilo_ticks = {ticks:,} ticks, more than the {FILE_TICKS_CAP:,} a "
                         f"command simulates by default; {hint}")
    return int(world.episode_steps)
