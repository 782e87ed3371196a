"""What the hand-written phototaxis kinds (``stop_in_light``, ``run_and_tumble``) share: the light walker as firmware.

Both are :class:`sim.tasks.phototaxis.LightWalker` rules: straight, or a pivot of 1..k periods in a random
direction, started where the rule says so; ``stop_in_light`` also stands while the held reading is above a
threshold, ``run_and_tumble`` also turns when the reading fell. Each kind's module gives its parameters, its
decision on the int8 ``light`` feature and its defines; this module holds the rest once: the float policy (an
artifact with no arrays, only the parameters, for task phototaxis), the integer rule, its state and its
random draws, the budget and the render spec (``firmware_templates/actors/light_rule.c.j2``, which each kind's
partial extends with its decision).

The integer rule runs the float rule's steps on the int8 observation every kind builds, with 6 bytes of state
(the xorshift32 word, the pivots left, the direction). Everything it compares is exact:

* **light**: the ``light`` feature's level ``lq`` and change ``dq`` are the held reading and its change at the
  input exponent (``(h · ONE) >> 10``; the float rule reads ``lq / ONE · 1024`` ADC counts). A comparison of the
  float rule in counts is an integer threshold on ``lq`` or ``dq`` (each kind's ``..._threshold``), as scaling by
  a power of two is exact.
* **draws**: each period the robot's xorshift32 word (:mod:`kiloforge.actors.rules`, seeded from ``kilo_uid``)
  is stepped once: its low half ``r`` (16 bits) decides a random turn (``r < TUMBLE_T``, ``TUMBLE_T =
  ceil(2**16 / run_steps)``, so exactly the float ``r / 2**16 < 1 / run_steps``), its byte 2 ``b`` the turn's
  pivots ``1 + (b · turn_max >> 8)`` and its byte 3 the direction (left when < 128).

:class:`FirmwareLightDraws` makes a float rule take its draws from these words: fed the dequantised observations
it gives exactly the integer rule's commands (the test of the integer reference). The float rules of
sim.tasks.phototaxis draw from NumPy, so the closed loop (float rule vs firmware) compares distributions.
"""
from __future__ import annotations

import dataclasses
from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.tasks import get_task
from sim.tasks.base import TaskRef
from sim.tasks.phototaxis import tumble_prob

from .. import numfmt
from ..artifact import plain_provenance
from ..errors import QuantizeError
from .base import (BudgetItem, BudgetOption, BudgetSpec, CDefine, FloatPolicy, QuantizedActor, RenderSpec, check_world_and_task,
                   invalid, sensing_tables)
from .rules import (PROB_BITS, PROB_ONE, SEED_ADD, SEED_MUL, RuleActor, RuleKind, UidStreams, draw_bytes,
                    params_from_meta, prob_threshold, rng_seed, xorshift32)

STATE_BYTES = 4 + 2  #: rng (uint32) + turn_left, turn_dir (uint8)
FEATURE = "light"  #: the observation feature the rules read
TASK = "phototaxis"  #: the task the rules are for
LEVEL_BITS = 10  #: the light feature's level is (h · ONE) >> 10: ADC counts = level · 2**10 / ONE


def firmware_draws(word: np.ndarray, turn_max: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The period's draws from its xorshift32 word: the 16-bit turn number, the turn's pivots, its direction
    (True: left)."""
    b = draw_bytes(word)
    return b[..., 0] | (b[..., 1] << 8), 1 + ((b[..., 2] * int(turn_max)) >> 8), b[..., 3] < 128


def level_threshold(counts: int, one: int) -> int:
    """The least int8 level ``lq`` with ``lq · 2**10 / one >= counts``: ``level >= counts`` exactly."""
    return -((-int(counts) * int(one)) >> LEVEL_BITS)


def fall_threshold(counts: int, one: int) -> int:
    """The least int8 change ``dq`` with ``dq · 2**10 / one >= -counts``: ``change < -counts`` is ``dq <`` this."""
    return -((int(counts) * int(one)) >> LEVEL_BITS)


# --------------------------------------------------------------------------------------------
# The float rule's random draws from the firmware's streams
# --------------------------------------------------------------------------------------------
class FirmwareLightDraws(UidStreams):
    """Mixin of a sim.tasks.phototaxis light rule drawing from the firmware's xorshift32 streams (one per robot,
    seeded by uid)."""

    def draws(self, shape: tuple[int, ...], turn_max: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.word = xorshift32(self.word)
        r, steps, left = firmware_draws(self.word, turn_max)
        return r / PROB_ONE, steps, left


# --------------------------------------------------------------------------------------------
# The float policy (the artifact)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LightRulePolicy(FloatPolicy):
    """A light rule with its parameters in a world; no arrays. A kind's subclass names its kind, its parameter
    class and its float rule (a sim.tasks.phototaxis LightWalker taking ``(world, params)``, own seeds)."""

    params_cls: ClassVar[type]
    seeded_cls: ClassVar[type]
    label: ClassVar[str]  #: the rule's name in one-line descriptions
    params: Any
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    task: TaskRef | None = None

    def __post_init__(self) -> None:
        check_world_and_task(self.world, self.task)
        if not isinstance(self.params, self.params_cls):
            invalid(f"params must be {self.params_cls.__name__}, got {type(self.params).__name__}")
        if not self.world.has_feature(FEATURE):
            invalid(f"the {self.kind} rule reads the {FEATURE} feature; world '{self.world.name}' observes "
                    f"{self.world.obs_features}")
        object.__setattr__(self, "provenance", plain_provenance(self.provenance))

    @property
    def layer_sizes(self) -> list[int]:
        """[tuple width, 2]: no layers, the rule reads one tuple."""
        return [self.world.tuple_dim, ACTION_DIM]

    def describe(self) -> str:
        fields = ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(self.params).items())
        return f"hand-written {self.label} ({fields})"

    def arrays(self) -> dict[str, np.ndarray]:
        return {}

    def kind_meta(self) -> dict[str, Any]:
        return {"params": dataclasses.asdict(self.params)}

    def initial_state(self, n: int) -> Any:
        """A float rule of n robots (its own generator, seed 0)."""
        s = self.seeded_cls(self.world, self.params)
        s.reset(1, n)
        return s

    def step(self, x: np.ndarray, state: Any) -> tuple[np.ndarray, Any]:
        """Tuples (n, D) -> the rule's commands on their observation part (the state is updated in place)."""
        obs = np.asarray(x, np.float64)[:, ACTION_DIM:]
        return state.act(obs[None])[0], state


def task_policy(cls: type, world: WorldConfig, params: Any, provenance: Mapping[str, Any] | None) -> Any:
    """The ``cls`` artifact of task phototaxis in ``world`` made the task's (default: the tuned parameters)."""
    task = get_task(TASK)
    notes = f"sim.tasks.phototaxis, {cls.params_cls.__name__} tuned on validation episodes (tools/tune_phototaxis.py)"
    return cls(params if params is not None else cls.params_cls(), task.world(world),
               dict(provenance or {"notes": notes}), task.ref)


# --------------------------------------------------------------------------------------------
# The integer rule
# --------------------------------------------------------------------------------------------
@dataclass
class LightRuleState:
    """Per robot (R,): the firmware's light-rule fields."""

    rng: np.ndarray  #: uint32 xorshift32 word
    turn_left: np.ndarray  #: pivot periods still to do (0..255)
    turn_dir: np.ndarray  #: bool, True: left


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedLightRule(RuleActor, QuantizedActor):
    """The integer light rule (module doc); a kind's subclass says where robots stand and where they turn."""

    params: Any
    tumble_t: int  #: a walking robot starts a random turn when the 16-bit draw < tumble_t

    def __post_init__(self) -> None:
        super().__post_init__()
        assert 0 <= self.tumble_t <= PROB_ONE, "tumble_t out of range"

    @abstractmethod
    def decide(self, level: np.ndarray, change: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """int64 light level and change (R,) at e_in -> (stand, turn) (R,) bool, the kind's rule."""

    def setup_state(self, uids: np.ndarray) -> LightRuleState:
        """What setup() leaves: the turn fields 0, the generator seeded from kilo_uid."""
        z = np.zeros(np.asarray(uids).shape[0], np.int64)
        return LightRuleState(rng=rng_seed(uids), turn_left=z, turn_dir=z.astype(bool))

    def step_int(self, x: np.ndarray, state: LightRuleState) -> tuple[np.ndarray, LightRuleState]:
        """int8 tuples (R, D) and the state -> (uint8 commands (R, 2), the new state); the float rule's steps."""
        o = np.asarray(x, np.int64)[:, ACTION_DIM:]
        i = self.world.obs_index(FEATURE)
        stand, turn = self.decide(o[:, i], o[:, i + 1])
        w = xorshift32(state.rng)
        r, steps, left = firmware_draws(w, self.params.turn_max_steps)
        start = (turn | (r < self.tumble_t)) & (state.turn_left == 0) & ~stand
        turn_left = np.where(start, steps, state.turn_left)
        turn_dir = np.where(start, left, state.turn_dir)
        turning = ~stand & (turn_left > 0)
        q = np.zeros((o.shape[0], ACTION_DIM), np.uint8)
        q[:, 0] = np.where(turning, np.where(turn_dir, 0, 255), np.where(stand, 0, 255))
        q[:, 1] = np.where(turning, np.where(turn_dir, 255, 0), np.where(stand, 0, 255))
        return q, LightRuleState(rng=w, turn_left=np.where(turning, turn_left - 1, turn_left), turn_dir=turn_dir)

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "params": dataclasses.asdict(self.params), "tumble_t": int(self.tumble_t), "prob_bits": PROB_BITS,
                **self.thresholds(),
                "rng": "xorshift32 (13, 17, 5) stepped once per period, seed kilo_uid * 0x9E3779B1 + 0x7F4A7C15",
                "policy_hash": self.policy_hash, "world": self.world.name}

    @abstractmethod
    def thresholds(self) -> dict[str, int]:
        """The kind's light thresholds at e_in (manifest)."""


def quantize_light_rule(cls: type, policy: LightRulePolicy, e_in: int | None, **thresholds: Any) -> Any:
    """The integer rule ``cls`` of ``policy``; ``thresholds`` maps a field to ``f(one)`` (its value at e_in)."""
    e = numfmt.DEFAULT_INPUT_EXP if e_in is None else int(e_in)
    if not 0 <= e <= numfmt.DEFAULT_INPUT_EXP:
        raise QuantizeError(f"e_in must be in 0..{numfmt.DEFAULT_INPUT_EXP}, got {e}")
    w = policy.world
    return cls(params=policy.params, tumble_t=int(prob_threshold(tumble_prob(policy.params))), e_in=e, world=w,
               policy_hash=policy.hash, **{k: f(1 << e) for k, f in thresholds.items()}, **sensing_tables(w, e))


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LightRuleArch:
    """A light rule's size does not vary: a fixed state, a few defines, the rule."""


#: code beside the base estimate: the rule and xorshift32 minus the dense kernels the base counts and this program
#: leaves out; measured: avr-gcc 9,364 B (stop_in_light) / 9,338 B (run_and_tumble) flash for the kilobot world's rules
#: against 9,265 B analytic at this value
CODE_B = -3_750


class LightRuleKind(RuleKind):
    """A hand-written phototaxis rule as firmware; a subclass names its policy, integer rule and extra defines."""

    arch = LightRuleArch
    policy_cls: ClassVar[type]
    draw_cls: ClassVar[type]  #: the float rule with FirmwareLightDraws

    @property
    def flag(self) -> str:
        """Its flag of ``python -m export budget``: the name with dashes."""
        return "--" + self.name.replace("_", "-")

    @property
    def budget_usage(self) -> str:  # type: ignore[override]
        return f"{self.flag} tuned"

    @property
    def budget_options(self) -> tuple[BudgetOption, ...]:  # type: ignore[override]
        return (BudgetOption(self.flag, f"the hand-written {self.policy_cls.label} rule (its size does not depend on "
                             "its parameters)", metavar="RULE", positive=False, choices=("tuned",)),)

    def policy_of(self, meta_params: Any, world: WorldConfig, provenance: dict[str, Any]) -> LightRulePolicy:
        return self.policy_cls(params_from_meta(self.policy_cls.params_cls, meta_params), world, provenance)

    def swarm_policy(self, policy: LightRulePolicy, world: WorldConfig | None = None) -> Any:
        """The float rule of sim.tasks.phototaxis (its own generator unless reset gets one)."""
        return policy.seeded_cls(world or policy.world, policy.params)

    def draw_reference(self, policy: LightRulePolicy, uids: np.ndarray) -> Any:
        return self.draw_cls(policy.world, policy.params, uids)

    def budget_spec(self, world: WorldConfig, arch: LightRuleArch, e_in: int) -> BudgetSpec:
        return BudgetSpec(
            header=f"hand-written {self.name} (no dense layers)", layer_sizes=(world.tuple_dim, ACTION_DIM), dense=(),
            memory=(BudgetItem("sram", f"{self.name} state", STATE_BYTES, "rng (4 B) + turn, direction"),),
            scratch=(BudgetItem("sram", "tuple buffer", world.tuple_dim, f"{world.tuple_dim} int8"),),
            code_b=CODE_B, code_note=f"(the {self.name} rule, without the dense kernels; estimate)")

    @abstractmethod
    def rule_defines(self, qp: QuantizedLightRule) -> tuple[CDefine, ...]:
        """The kind's own defines (its light thresholds)."""

    def render_spec(self, qp: QuantizedLightRule) -> RenderSpec:
        p = qp.params
        return RenderSpec(
            memory=(),
            scratch=self.rule_defines(qp) + (
                CDefine("KF_TUMBLE_T", qp.tumble_t, "uint32_t",
                        f"start a random turn when the 16-bit draw < this (1 / {p.run_steps} of 2^16)"),
                CDefine("KF_TURN_MAX", p.turn_max_steps, comment="a random turn pivots 1..this many periods"),
                CDefine("KF_SEED_MUL", SEED_MUL, "uint32_t", "xorshift32 seed = kilo_uid * MUL + ADD (never 0)"),
                CDefine("KF_SEED_ADD", SEED_ADD, "uint32_t"),
            ),
            tables=())
