"""Actor kind ``"run_and_tumble"``: the hand-written run-and-tumble rule of :mod:`sim.tasks.phototaxis` as firmware.

The float actor is :class:`sim.tasks.phototaxis.RunAndTumble` (straight while the reading holds or rises; a
random turn when it fell by more than ``fall`` ADC counts since the last period, and now and then at random);
its artifact holds only the :class:`~sim.tasks.phototaxis.RunAndTumbleParams` and records task phototaxis. The
shipped one is ``export/data/run_and_tumble_policy.npz``, written by ``python -m tools.ship_rules``. The
integer rule turns where the int8 light change ``dq < KF_FALL_T = ceil(-fall · ONE / 2**10)``, exactly the
float ``change < -fall`` on ``dq / ONE · 2**10`` counts (at the default e_in a level step is 16 counts, so the
tuned fall of 12 counts is any step down); the walk, its draws and the rest are :mod:`.light_rules`'.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import WorldConfig
from sim.tasks.phototaxis import RunAndTumble, RunAndTumbleParams

from .base import CDefine
from .light_rules import (LEVEL_BITS, FirmwareLightDraws, LightRuleKind, LightRulePolicy, QuantizedLightRule,
                          fall_threshold, quantize_light_rule, task_policy)
from .rules import OwnSeeds


class SeededRunAndTumble(OwnSeeds, RunAndTumble):
    """The float rule; ``reset`` without a generator takes the next child of its own seed sequence."""


class FirmwareDrawRunAndTumble(FirmwareLightDraws, RunAndTumble):
    """The float rule drawing from the firmware's xorshift32 streams (one per robot, seeded by uid)."""


@dataclass(frozen=True, eq=False)
class RunAndTumblePolicy(LightRulePolicy):
    """The run-and-tumble rule with its parameters in a world; no arrays."""

    kind: ClassVar[str] = "run_and_tumble"
    params_cls: ClassVar[type] = RunAndTumbleParams
    seeded_cls: ClassVar[type] = SeededRunAndTumble
    label: ClassVar[str] = "run-and-tumble"


def run_and_tumble_policy(world: WorldConfig, params: RunAndTumbleParams | None = None,
                          provenance: Mapping[str, Any] | None = None) -> RunAndTumblePolicy:
    """The run_and_tumble artifact of task phototaxis in ``world`` made the task's (default: the tuned parameters)."""
    return task_policy(RunAndTumblePolicy, world, params, provenance)


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedRunAndTumble(QuantizedLightRule):
    """The integer rule: never stand; turn where the light change < fall_t."""

    kind: ClassVar[str] = "run_and_tumble"
    fall_t: int  #: turn when the int8 change < this (-fall at e_in, rounded up)

    def decide(self, level: np.ndarray, change: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(change.shape, bool), change < self.fall_t

    def thresholds(self) -> dict[str, int]:
        return {"fall_t": int(self.fall_t)}

    def describe(self) -> str:
        return (f"hand-written run-and-tumble: turn at light change < {self.fall_t} (of {1 << self.e_in} per "
                f"{1 << LEVEL_BITS} counts), random turns out of 2^16, e_in {self.e_in}")


def quantize_run_and_tumble(policy: RunAndTumblePolicy, e_in: int | None = None) -> QuantizedRunAndTumble:
    """The integer rule of ``policy``."""
    return quantize_light_rule(QuantizedRunAndTumble, policy, e_in,
                               fall_t=lambda one: fall_threshold(policy.params.fall, one))


class RunAndTumbleKind(LightRuleKind):
    """The run-and-tumble rule of sim.tasks.phototaxis (a baseline to flash next to a learned policy)."""

    name: ClassVar[str] = "run_and_tumble"
    template: ClassVar[str] = "actors/run_and_tumble.c.j2"
    policy_cls = RunAndTumblePolicy
    draw_cls = FirmwareDrawRunAndTumble

    def quantize_rule(self, policy: RunAndTumblePolicy, e_in: int | None) -> QuantizedRunAndTumble:
        return quantize_run_and_tumble(policy, e_in)

    def rule_defines(self, qp: QuantizedRunAndTumble) -> tuple[CDefine, ...]:
        return (CDefine("KF_FALL_T", qp.fall_t, "int16_t",
                        f"turn when the light change < this (-{qp.params.fall} counts at e_in, rounded up)"),)


RUN_AND_TUMBLE = RunAndTumbleKind()
