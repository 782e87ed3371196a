"""Actor kind ``"shadow_pusher"``: the hand-written transport rule of :mod:`sim.tasks.transport` as firmware.

The float actor is :class:`sim.tasks.transport.ShadowPusher` (run and tumble up the light in the dark and down it
when lit; near the object: head for it in the dark and push, turn away when lit, turn back on losing its signal);
its artifact holds only the :class:`~sim.tasks.transport.ShadowPusherParams` and records task transport. The
shipped one is ``export/data/shadow_pusher_policy.npz``, written by ``python -m tools.ship_rules``.

The integer rule runs the float rule's steps on the int8 observation (``light`` level ``lq`` and change ``dq``,
``target`` ``tq`` at ``e_in``) with 8 bytes of state (the xorshift32 word, the pivots left, the direction, whether
the object was heard and its ``tq`` then). Everything it compares is exact:

* **light**: ``dark`` is ``lq < level_threshold(dark)``, the fall ``dq < fall_threshold(fall)`` (both of
  :mod:`.light_rules`), the rise ``dq > RISE_T = (rise · ONE) >> 10``: the float comparisons on ``lq / ONE · 2**10``
  counts, as scaling by a power of two is exact.
* **distance**: the float rule reads ``d = t · comm_radius_mm`` with ``t = tq / ONE``; ``touching`` is ``tq <=
  TOUCH_T`` and "the distance grew by more than back_mm" is ``tq - tq_prev > BACK_T``, both found by evaluating the
  float expressions over every int8 value (pair) at quantisation time, which refuses a world where no such
  threshold exists (QuantizeError).
* **draws**: those of :mod:`.light_rules` (one xorshift32 step per period: the 16-bit turn draw, the pivots, the
  direction); a lost signal turns ``back_steps`` periods in the drawn direction.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.tasks import get_task
from sim.tasks.transport import ShadowPusher, ShadowPusherParams

from .. import numfmt
from ..errors import QuantizeError
from .base import BudgetItem, BudgetSpec, CDefine, QuantizedActor, RenderSpec, sensing_tables
from .light_rules import (LEVEL_BITS, STATE_BYTES as WALK_BYTES, FirmwareLightDraws, LightRuleKind, LightRulePolicy,
                          fall_threshold, firmware_draws, level_threshold)
from .rules import PROB_BITS, OwnSeeds, RuleActor, prob_threshold, rng_seed, xorshift32

STATE_BYTES = WALK_BYTES + 2  #: the walk's (rng, turn, direction) + heard, tq_prev (uint8, int8)
TASK = "transport"  #: the task the rule is for


class SeededShadowPusher(OwnSeeds, ShadowPusher):
    """The float rule; ``reset`` without a generator takes the next child of its own seed sequence."""


class FirmwareDrawShadowPusher(FirmwareLightDraws, ShadowPusher):
    """The float rule drawing from the firmware's xorshift32 streams (one per robot, seeded by uid)."""


@dataclass(frozen=True, eq=False)
class ShadowPusherPolicy(LightRulePolicy):
    """The shadow-pusher rule with its parameters in a world; no arrays."""

    kind: ClassVar[str] = "shadow_pusher"
    params_cls: ClassVar[type] = ShadowPusherParams
    seeded_cls: ClassVar[type] = SeededShadowPusher
    label: ClassVar[str] = "shadow pusher"


def shadow_pusher_policy(world: WorldConfig, params: ShadowPusherParams | None = None,
                         provenance: Mapping[str, Any] | None = None) -> ShadowPusherPolicy:
    """The shadow_pusher artifact of task transport in ``world`` made the task's (default: the tuned parameters)."""
    task = get_task(TASK)
    notes = "sim.tasks.transport, ShadowPusherParams tuned on validation episodes (tools/tune_transport.py)"
    return ShadowPusherPolicy(params if params is not None else ShadowPusherParams(), task.world(world),
                              dict(provenance or {"notes": notes}), task.ref)


def distance_thresholds(p: ShadowPusherParams, comm_radius_mm: float, one: int) -> tuple[int, int]:
    """(TOUCH_T, BACK_T): for heard int8 targets tq, tq_prev >= 0, the float ``tq / one · comm <= touch_mm`` is
    ``tq <= TOUCH_T`` and ``d > d_prev + back_mm`` is ``tq - tq_prev > BACK_T``. QuantizeError when no integer
    threshold decides as the float rule does."""
    k = np.arange(0, 128)
    d = (k / one) * comm_radius_mm  # as the float rule computes it from the dequantised observation
    touch_t = int(k[d <= p.touch_mm].max(initial=-1))
    grew = d[:, None] > d[None, :] + p.back_mm  # (tq, tq_prev)
    diff = k[:, None] - k[None, :]
    back_t = int(diff[~grew].max())
    if not np.array_equal(grew, diff > back_t) or not np.array_equal(d <= p.touch_mm, k <= touch_t):
        raise QuantizeError(f"shadow_pusher: no integer distance thresholds match the float rule at e_in with "
                            f"comm_radius_mm {comm_radius_mm:g}")
    return touch_t, back_t


@dataclass
class ShadowPusherState:
    """Per robot (R,): the firmware's rule fields."""

    rng: np.ndarray  #: uint32 xorshift32 word
    turn_left: np.ndarray  #: pivot periods still to do (0..255)
    turn_dir: np.ndarray  #: bool, True: left
    heard: np.ndarray  #: bool, the object's robot was heard last period
    tq_prev: np.ndarray  #: int8 target input last period


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedShadowPusher(RuleActor, QuantizedActor):
    """The integer shadow pusher (module doc)."""

    kind: ClassVar[str] = "shadow_pusher"
    params: ShadowPusherParams
    tumble_t: int  #: a random turn starts when the 16-bit draw < tumble_t
    dark_t: int  #: dark: the int8 light level < this
    fall_t: int  #: the reading fell: the int8 change < this
    rise_t: int  #: the reading rose: the int8 change > this
    touch_t: int  #: touching: the int8 target input <= this
    back_t: int  #: the distance grew: the target input rose by more than this

    def setup_state(self, uids: np.ndarray) -> ShadowPusherState:
        """What setup() leaves: every field 0, the generator seeded from kilo_uid."""
        z = np.zeros(np.asarray(uids).shape[0], np.int64)
        return ShadowPusherState(rng=rng_seed(uids), turn_left=z, turn_dir=z.astype(bool), heard=z.astype(bool),
                                 tq_prev=z.copy())

    def step_int(self, x: np.ndarray, state: ShadowPusherState) -> tuple[np.ndarray, ShadowPusherState]:
        """int8 tuples (R, D) and the state -> (uint8 commands (R, 2), the new state); the float rule's steps."""
        p = self.params
        o = np.asarray(x, np.int64)[:, ACTION_DIM:]
        il, it = self.world.obs_index("light"), self.world.obs_index("target")
        lq, dq, tq = o[:, il], o[:, il + 1], o[:, it]
        heard = tq >= 0
        touching = heard & (tq <= self.touch_t)
        dark = lq < self.dark_t
        near = dark & heard
        away = state.heard & (tq - state.tq_prev > self.back_t)
        lost = state.heard & ~heard
        push = dark & touching
        wrong = np.where(near, away, np.where(dark, dq < self.fall_t, (dq > self.rise_t) | touching))
        w = xorshift32(state.rng)
        r, steps, left = firmware_draws(w, p.turn_max_steps)
        tumble = ~push & (wrong | (~near & (r < self.tumble_t)))
        start = (tumble & (state.turn_left == 0)) | (lost & (p.back_steps > 0))
        turn_left = np.where(push, 0, np.where(start, np.where(lost, p.back_steps, steps), state.turn_left))
        turn_dir = np.where(start, left, state.turn_dir)
        turning = turn_left > 0
        q = np.full((o.shape[0], ACTION_DIM), 255, np.uint8)
        q[:, 0] = np.where(turning & ~turn_dir, 0, 255)
        q[:, 1] = np.where(turning & turn_dir, 0, 255)
        return q, ShadowPusherState(rng=w, turn_left=np.maximum(turn_left - 1, 0), turn_dir=turn_dir, heard=heard,
                                    tq_prev=tq)

    def thresholds(self) -> dict[str, int]:
        return {k: int(getattr(self, k)) for k in ("dark_t", "fall_t", "rise_t", "touch_t", "back_t")}

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "params": dataclasses.asdict(self.params), "tumble_t": int(self.tumble_t), "prob_bits": PROB_BITS,
                **self.thresholds(),
                "rng": "xorshift32 (13, 17, 5) stepped once per period, seed kilo_uid * 0x9E3779B1 + 0x7F4A7C15",
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        return (f"hand-written shadow pusher: dark at light level < {self.dark_t} (of {1 << self.e_in} per "
                f"{1 << LEVEL_BITS} counts), touching at target <= {self.touch_t}, random turns out of 2^16, "
                f"e_in {self.e_in}")


def quantize_shadow_pusher(policy: ShadowPusherPolicy, e_in: int | None = None) -> QuantizedShadowPusher:
    """The integer rule of ``policy``."""
    e = numfmt.DEFAULT_INPUT_EXP if e_in is None else int(e_in)
    if not 0 <= e <= numfmt.DEFAULT_INPUT_EXP:
        raise QuantizeError(f"e_in must be in 0..{numfmt.DEFAULT_INPUT_EXP}, got {e}")
    p, w, one = policy.params, policy.world, 1 << e
    touch_t, back_t = distance_thresholds(p, w.comm_radius_mm, one)
    return QuantizedShadowPusher(
        params=p, tumble_t=int(prob_threshold(1.0 / p.run_steps)), dark_t=level_threshold(p.dark, one),
        fall_t=fall_threshold(p.fall, one), rise_t=(p.rise * one) >> LEVEL_BITS, touch_t=touch_t, back_t=back_t,
        e_in=e, world=w, policy_hash=policy.hash, **sensing_tables(w, e))


class ShadowPusherKind(LightRuleKind):
    """The shadow-pusher rule of sim.tasks.transport (a baseline to flash next to a learned policy)."""

    name: ClassVar[str] = "shadow_pusher"
    template: ClassVar[str] = "actors/shadow_pusher.c.j2"
    policy_cls = ShadowPusherPolicy
    draw_cls = FirmwareDrawShadowPusher

    def quantize_rule(self, policy: ShadowPusherPolicy, e_in: int | None) -> QuantizedShadowPusher:
        return quantize_shadow_pusher(policy, e_in)

    def budget_spec(self, world: WorldConfig, arch: Any, e_in: int) -> BudgetSpec:
        spec = super().budget_spec(world, arch, e_in)
        return dataclasses.replace(spec, memory=(BudgetItem("sram", f"{self.name} state", STATE_BYTES,
                                                            "rng (4 B) + turn, direction, heard, target"),))

    def rule_defines(self, qp: QuantizedShadowPusher) -> tuple[CDefine, ...]:
        p = qp.params
        return (CDefine("KF_DARK_T", qp.dark_t, "int16_t", f"dark: light level < this ({p.dark} counts at e_in)"),
                CDefine("KF_FALL_T", qp.fall_t, "int16_t", f"the reading fell: change < this (-{p.fall} counts)"),
                CDefine("KF_RISE_T", qp.rise_t, "int16_t", f"the reading rose: change > this ({p.rise} counts)"),
                CDefine("KF_TOUCH_T", qp.touch_t, "int16_t", f"touching: target input <= this ({p.touch_mm:g} mm)"),
                CDefine("KF_BACK_T", qp.back_t, "int16_t",
                        f"the distance grew: target input rose by more than this ({p.back_mm:g} mm)"),
                CDefine("KF_BACK_STEPS", p.back_steps, comment="losing the object's signal: pivot this many periods"))


SHADOW_PUSHER = ShadowPusherKind()
