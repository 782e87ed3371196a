"""Collective transport: robots push a heavy object, too heavy for one or two of them, towards a lamp.

The thesis's outlook (a task that needs cooperation: "cooperative box pushing, where objects, which are
too 'heavy' to be moved by a single agent, have to be moved from a starting place to a target
destination"); the Kilobot anchors are Rubenstein et al. (AAMAS 2013) and, for the rule "push where the
object hides the goal", Chen et al. (IEEE T-RO 2015, occlusion-based cooperative transport).

*World* (:meth:`Transport.world`): the beacon robot rides on a heavy disc of radius :data:`BODY_RADIUS_MM`
(:mod:`sim.body`) whose static friction :data:`PUSHERS` - 1 + :data:`FRICTION_MARGIN` full robot pushes hold: one
or two robots cannot move it, :data:`PUSHERS` robots pushing the same way can. A lamp at the +x side lights the table
in a gradient (``side:0,peak``, :mod:`sim.light`, walls unlit) and the object shades the floor behind it.
Sensing is a Kilobot's: the object's robot transmits (robots hear their distance to it, the ``target``
feature), the ambient-light sensor (the graded ``light`` feature: the shadow and the gradient), the
neighbours' distances (``rbf``). No bearings, no positions.

*Episode*: the goal zone is the strip of object centres within :data:`GOAL_DEPTH_MM` of the lamp's wall; the
object starts :data:`START_DISTANCE_MM` short of it along the lamp's direction (uniform in that range; across it,
y in [-2a/5, 2a/5]): in the kilobot arena its centre starts at x in [-30, 20] mm and the zone begins at x = 50 mm.
Robots start uniformly over the arena, off the object. :data:`EPISODE_STEPS` (500, the thesis benchmark's length,
which ``learn evaluate`` runs) with this start distance lets the hand-written rule bring the object into the zone in
about half the episodes at 16 robots (docs/results/transport.md).

*Success* of a step: the object's progress towards the goal, ``(x - x0) / (x_goal - x0)`` along the lamp's
direction, clipped to [0, 1]; ``final_displacement`` is its mean over the last quarter of the episode (every
task's *final*), ``success_rate`` the fraction of episodes whose object is in the goal zone at the end.
Team reward: ``scale · (success² - penalty · mean ||a||²)``. Critic state: the object's position and
every robot's pose.

*Baselines*: :class:`ShadowPusher` (find the object's dark side, get into its shadow, push; tuned on validation
episodes, ``python -m tools.tune_transport``) and the random walk.
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
from ..kinematics import wrap_angle
from ..light import ADC_MAX
from ..metrics import SuccessMetrics, Summary, summarise
from .base import Metric, Task, squared_success_reward
from .localisation import Localisation
from .phototaxis import SENSOR

BODY_RADIUS_MM = 60.0  #: the object's radius: a robot touching it is 76.5 mm from its robot, within radio range
PUSHERS = 3  #: robots pushing the same way that move the object (k: its friction is k - 1 + FRICTION_MARGIN pushes)
#: k - 1 full pushes (at most k - 1 robots) never move the object; k pushing within about ±50° of each other do
FRICTION_MARGIN = 0.2
LAMP_PEAK = 900  #: ADC counts the side lamp adds at its wall (0 at the opposite wall)
GOAL_DEPTH_MM = 200.0  #: the goal zone: object centres within this of the lamp's wall
EPISODE_STEPS = 500  #: control periods per episode (the hand-written rule needs most of them)
#: the object's start: this far (mm, uniform) short of the goal zone along the lamp's direction. At 16 robots the
#: hand-written rule moves the object about 35 mm in 500 periods on average (gathering three pushers takes most of them)
START_DISTANCE_MM = (30.0, 80.0)
START_Y = 0.4  #: the object's start |y| at most, as a fraction of arena_half_mm


def side_lamp(cfg: WorldConfig):
    """The world's goal lamp: its first ``side`` lamp (None when it has none)."""
    return next((lamp for lamp in cfg.lamp_list if lamp.kind == "side"), None)


@dataclass
class TransportMetrics(SuccessMetrics):
    """:class:`sim.metrics.SuccessMetrics` and the success rate: the object in the goal zone at the end."""

    def per_episode(self, key: str) -> np.ndarray:
        if key == "success_rate":
            return (self.success[:, -1] >= 1.0).astype(np.float64)
        return super().per_episode(key)

    def summary(self) -> dict[str, Summary]:
        s = super().summary()
        s["success_rate"] = summarise(self.per_episode("success_rate"))
        return s

    def to_dict(self, per_episode: bool = True) -> dict:
        d = super().to_dict(per_episode)
        if per_episode:
            d["per_episode"]["success_rate"] = self.per_episode("success_rate").tolist()
        return d


class Transport(Task):
    name = "transport"
    version = 2
    description = "robots push a heavy object, which no one or two of them can move, towards a lamp (cooperation)"
    beacon_role = "the object's robot"
    success_label = "object's progress to the goal"
    robot_label = "touching the object"
    primary_metric = "final_displacement"
    mean_metric = "mean_displacement"
    metrics = (Metric("final_displacement", "final displ", name="final displacement towards the goal (fraction)"),
               Metric("success_rate", "in goal"),
               Metric("mean_displacement", "mean displ"),
               Metric("return", "return"))
    baselines = {"hand-written shadow pusher": "shadow_pusher", "random": "random"}
    beacon = True
    features = ("light", "target", "rbf")
    firmware = "transport"  #: firmware_templates/tasks/transport/ (localisation's beacon role, for the object's robot)
    emitter_program = Localisation.emitter_program

    def world(self, cfg: WorldConfig) -> WorldConfig:
        """The task's layout; a world without a heavy body gets the object, the side lamp (walls unlit), the
        sensor model of phototaxis and the task's episode length."""
        cfg = super().world(cfg)
        if cfg.body_radius_mm > 0:
            return cfg
        if not (cfg.collisions and cfg.robot_radius_mm > 0):
            raise InputError(f"task 'transport' needs a world where robot discs collide (robots push the object), "
                             f"e.g. --world kilobot; world '{cfg.name}' has point robots or no collisions")
        return dataclasses.replace(cfg, body_radius_mm=BODY_RADIUS_MM, body_friction=PUSHERS - 1 + FRICTION_MARGIN,
                                   lamps=f"side:0,{LAMP_PEAK}", light_wall=cfg.light_floor,
                                   episode_steps=EPISODE_STEPS, **SENSOR)

    def check_world(self, cfg: WorldConfig) -> None:
        super().check_world(cfg)
        if cfg.body_radius_mm <= 0 or side_lamp(cfg) is None:
            raise InputError(f"world '{cfg.name}' has no heavy body or no side lamp (body_radius_mm "
                             f"{cfg.body_radius_mm:g}, lamps {cfg.lamps!r}); task 'transport' needs both "
                             "(Task.world(cfg) makes them)")
        room = cfg.arena_half_mm - cfg.body_radius_mm  # the object's centre stays within this of the middle
        goal = self.goal_along(cfg)
        if not (-room <= goal - START_DISTANCE_MM[1] and goal < room):
            raise InputError(f"world '{cfg.name}': arena_half_mm {cfg.arena_half_mm:g} has no room for the object's "
                             f"start {START_DISTANCE_MM[1]:g} mm short of a goal zone {GOAL_DEPTH_MM:g} mm deep")

    # --- geometry ---------------------------------------------------------------------------------
    def _axis(self, cfg: WorldConfig) -> np.ndarray:
        a = math.radians(side_lamp(cfg).angle_deg)
        return np.array([math.cos(a), math.sin(a)])

    def goal_along(self, cfg: WorldConfig) -> float:
        """The goal line: object centres beyond this along the lamp's direction are in the goal zone."""
        return cfg.arena_half_mm - GOAL_DEPTH_MM

    def progress(self, cfg: WorldConfig, start: np.ndarray, body: np.ndarray) -> np.ndarray:
        """(B,) the object's displacement towards the goal as a fraction of the start distance (unclipped)."""
        u = self._axis(cfg)
        s0 = start @ u
        return (body @ u - s0) / (self.goal_along(cfg) - s0)

    # --- the task interface -----------------------------------------------------------------------
    def spawn(self, env) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The object :data:`START_DISTANCE_MM` short of the goal zone, robots uniform over the arena (the env redraws
        those on the object)."""
        cfg, B, M = env.cfg, env.n_envs, env.n_robots
        a, h = cfg.arena_half_mm, env.spawn_box()
        u = self._axis(cfg)
        body = np.empty((B, 2))
        pos = np.empty((B, M, 2))
        heading = np.empty((B, M))
        for e, rng in enumerate(env.init_streams):  # loop over envs: each owns its generator
            along = self.goal_along(cfg) - rng.uniform(*START_DISTANCE_MM)
            across = rng.uniform(-START_Y * a, START_Y * a)
            body[e] = along * u + across * np.array([-u[1], u[0]])
            pos[e] = rng.uniform(-h, h, (M, 2))
            heading[e] = rng.uniform(-math.pi, math.pi, M)
        env.body_start = body.copy()  # where progress is measured from
        return body, pos, wrap_angle(heading)

    def step_info(self, env) -> dict[str, np.ndarray]:
        cfg = env.cfg
        progress = self.progress(cfg, env.body_start, env.target)
        touching = env.target_dist <= cfg.body_radius_mm + cfg.robot_radius_mm + 1.0
        return {"progress": progress, "success": np.clip(progress, 0.0, 1.0), "robot_success": touching}

    def reward(self, env, u: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return squared_success_reward(env, u, info["success"])

    #: the critic's state: the object's position (the beacon's) and every robot's pose, as localisation's
    state_dim = Localisation.state_dim
    state = Localisation.state

    def make_baseline(self, name: str, cfg: WorldConfig) -> Any:
        if name == "shadow_pusher":
            return ShadowPusher(cfg)
        from ..baselines import make_policy

        return make_policy(name, cfg)

    def episode_metrics(self, cfg: WorldConfig, n_robots: int, rewards: np.ndarray, success: np.ndarray,
                        beacon: np.ndarray | None, ceiling: bool = False) -> TransportMetrics:
        from ..metrics import final_success

        r, c = np.asarray(rewards, np.float64), np.asarray(success, np.float64)
        return TransportMetrics(c, r.sum(axis=1), final_success(c), self.primary_metric, self.mean_metric)


# ------------------------------------------------------------------------------------------------
# The hand-written baseline
# ------------------------------------------------------------------------------------------------
#: each ShadowPusherParams field's range: what the firmware's integer rule holds (readings 0..1023, uint8 periods)
PARAM_RANGES = {"dark": (0, ADC_MAX), "fall": (0, ADC_MAX), "rise": (0, ADC_MAX), "back_mm": (0.0, 255.0),
                "touch_mm": (0.0, 255.0), "run_steps": (1, 0xFFFF), "turn_max_steps": (1, COUNTER_MAX),
                "back_steps": (0, COUNTER_MAX)}


@dataclass(frozen=True)
class ShadowPusherParams:
    """Constants of :class:`ShadowPusher`, tuned by ``python -m tools.tune_transport`` (validation seed 777, 16 robots,
    100 episodes: final displacement 0.666, 49 % in the goal zone). Each is checked against :data:`PARAM_RANGES`
    (InputError naming it and its range)."""

    dark: int = 650  #: dark (the object's shadow, or far from the lamp): a held reading below this (ADC counts)
    fall: int = 5  #: dark: turn when the reading fell by more than this (heading away from the lamp)
    rise: int = 10  #: lit: turn when the reading rose by more than this (heading towards the lamp)
    back_mm: float = 4.0  #: dark near the object: turn when its distance grew by more than this (heading away)
    touch_mm: float = 79.0  #: pushing: the object's robot at most this far (touching it)
    run_steps: int = 20  #: besides, turn with probability 1 / this per period (exploration)
    turn_max_steps: int = 3  #: a turn pivots 1..this many periods
    back_steps: int = 4  #: having lost the object's signal, pivot this many periods (45° each; 0: never)

    def __post_init__(self) -> None:
        check_fields(self, PARAM_RANGES, "shadow_pusher")


class ShadowPusher:
    """Occlusion-based transport with a Kilobot's senses (Chen et al. 2015's rule, the lamp as the goal). A robot in
    the dark (reading below ``dark``) runs up the light gradient, a lit one down it (run and tumble on the reading's
    change, and a random turn now and then), so robots gather along the line where the light crosses ``dark``, and
    those that stray into the object's shadow run up it to the object's back. Near the object (its robot heard):
    in the dark, head for it (turn when the distance grows) and, touching it, push straight on; lit and touching,
    turn away (no pushing from the lamp's side); losing its signal, turn back. Reads ``light`` (level and change) and
    ``target``. Vectorised over (B, M). Its random numbers come from :meth:`draws` (the firmware's twin draws them
    from xorshift32: kiloforge/actors/shadow_pusher.py)."""

    def __init__(self, cfg: WorldConfig, params: ShadowPusherParams | None = None) -> None:
        self.cfg = cfg
        self.p = params or ShadowPusherParams()
        self.i_light, self.i_target = cfg.obs_index("light"), cfg.obs_index("target")
        self.rng: np.random.Generator | None = None

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng
        shape = (n_envs, n_robots)
        self.turn_left = np.zeros(shape, np.int64)  # pivot periods still to do
        self.turn_dir = np.zeros(shape, bool)  # True: left (counter-clockwise)
        self.was_heard = np.zeros(shape, bool)  # the object's robot was heard last period ...
        self.prev_d = np.zeros(shape)  # ... at this distance

    def draws(self, shape: tuple[int, ...], turn_max: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One period's draws: uniform [0, 1) for a random turn, its pivot periods (1..turn_max), its direction
        (True: left)."""
        assert self.rng is not None, "ShadowPusher.act before reset"
        u = self.rng.random(shape)
        return u, self.rng.integers(1, turn_max + 1, shape), self.rng.random(shape) < 0.5

    def act(self, obs: np.ndarray) -> np.ndarray:
        p, shape = self.p, obs.shape[:2]
        level, change = obs[..., self.i_light] * 1024.0, obs[..., self.i_light + 1] * 1024.0
        t = obs[..., self.i_target]
        heard = t >= 0
        d = t * self.cfg.comm_radius_mm
        touching = heard & (d <= p.touch_mm)
        dark = level < p.dark
        near = dark & heard  # in the dark near the object: head for it
        away = self.was_heard & (d > self.prev_d + p.back_mm)
        lost = self.was_heard & ~heard  # the object's signal just ended: turn back
        self.was_heard, self.prev_d = heard, d
        push = dark & touching
        wrong = np.where(near, away, np.where(dark, change < -p.fall, (change > p.rise) | touching))
        u, steps, left = self.draws(shape, p.turn_max_steps)
        tumble = ~push & (wrong | (~near & (u < 1.0 / p.run_steps)))
        start = (tumble & (self.turn_left == 0)) | (lost & (p.back_steps > 0))
        self.turn_left = np.where(push, 0, np.where(start, np.where(lost, p.back_steps, steps), self.turn_left))
        self.turn_dir = np.where(start, left, self.turn_dir)
        turning = self.turn_left > 0
        a = np.ones(shape + (ACTION_DIM,))
        a[..., 0] = np.where(turning & ~self.turn_dir, 0.0, 1.0)  # (0, 1): a right pivot
        a[..., 1] = np.where(turning & self.turn_dir, 0.0, 1.0)  # (1, 0): a left pivot
        self.turn_left = np.maximum(self.turn_left - 1, 0)
        return a
